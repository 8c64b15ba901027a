"""A mesh's vertex colours from rendered images of the field: how a Gaussian-field avatar's exported mesh is coloured.

The head-on ray bake (`mesh.bake_colours`) reads a field at points just outside the surface; a Gaussian field's
surface of density lies ~2 cm outside most of its splats' centres and the bake sees a thin, partly transparent
fringe of them (on the demo capture's 90 s Gaussian fit, frame 0: mesh 19.75 dB against its volume render's 22.07;
docs/fit.md). What a person sees of that avatar are its rasterized images; so the mesh takes its colours from them.

Steps (`view_colours`):
1. cameras around the mesh (`surround_cameras`): `count` directions on a Fibonacci sphere about the capture's up
   axis, without the caps within acos(`pole`) of the up axis (straight down on the head, up from under the feet),
   each `distance` times the radius of the mesh's bounding sphere from its centre, looking at the centre, the
   focal length such that the sphere just fills the square image of `size` pixels;
2. per camera: the field's image, rgb premultiplied (over black) and alpha, from the caller (`ViewRenderFn`); one ray
   per pixel cast against the mesh itself (`raster.cast_pixels`): a vertex takes colour only from pixels where its
   own faces are what the camera sees (visibility exact for the mesh, no depth threshold); pixels where the field's
   alpha is below `min_alpha` are skipped (the mesh passes where the field is nearly empty);
3. a pixel's colour is rgb / alpha (the colour of what the field shows there) and goes to the hit face's three
   vertices with weight barycentric x cos^`power` (cos between the pixel's ray and the face's normal: pixels that
   see the surface head-on count most); a vertex's colour is its weighted mean;
4. vertices no pixel reached (inner folds, under the arms) take the colour of the nearest vertex that was reached
   (scipy's cKDTree); with none reached at all, every vertex is black and `seen` says so.

Measured (docs/export_view.md, step 4): on the demo capture's 90 s Gaussian fit the exported meshes score 21.14 dB
against the bake's 20.18 on the same surface (frames 0, 8, 16, 28, 2 held-out views each; the MLP fields' mesh at the
same fit time 20.68), on synth small's 10-minute fit 22.54 against 22.23; 2-4 s per mesh on 2 threads.

Conventions: pinhole cameras (OpenCV, world -> camera, metres), the mesh and cameras in the same world frame, faces
wound counter-clockwise seen from outside (outward normals), colours in [0, 1].
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable

import numpy as np

from avatarctl.export.raster import barycentric, cast_pixels
from avatarctl.geometry.cameras import Camera

if TYPE_CHECKING:
    from avatarctl.export.mesh import VertexColourFn
    from avatarctl.model.avatar import NodeState, SlrfAvatar

VIEW_COUNT = 44  # directions on the Fibonacci sphere (step 1; 40 of them outside the caps with POLE 0.9)
VIEW_SIZE = 256  # pixels, square
VIEW_DISTANCE = 3.0  # camera distance in bounding-sphere radii
POLE = 0.9  # |cos| to the up axis above which directions are skipped
POWER = 1.0  # cos^POWER weights head-on pixels (step 3)
MIN_ALPHA = 0.01  # field alpha below which a pixel gives no colour (step 3)
VIEW_RULE = (f"the field rasterized from the cameras of {VIEW_COUNT} directions around the mesh ({VIEW_SIZE} px, "
             f"those within acos {POLE:g} of the up axis skipped), each pixel of alpha >= {MIN_ALPHA:g} giving rgb / "
             f"alpha to the mesh face its ray hits (barycentric x cos^{POWER:g} weights; export.view_colours)")
ViewRenderFn = Callable[[Camera], tuple[np.ndarray, np.ndarray]]  # camera -> (rgb [H, W, 3] premultiplied over
#                                                                   black, alpha [H, W]), float32


@dataclass(frozen=True)
class ViewColours:
    """The outcome of `view_colours`."""

    colours: np.ndarray  # [V, 3] float32 in [0, 1]
    seen: np.ndarray  # [V] bool: coloured by some pixel (the rest: their nearest seen vertex's colour)
    views: int  # cameras rendered

    def __post_init__(self) -> None:
        V = self.seen.shape[0]
        assert self.colours.shape == (V, 3), f"colours: expected [{V}, 3], got {self.colours.shape}"


def surround_cameras(vertices: np.ndarray, up: np.ndarray, count: int = VIEW_COUNT, size: int = VIEW_SIZE,
                     distance: float = VIEW_DISTANCE, pole: float = POLE) -> list[Camera]:
    """Step 1: pinhole cameras around the points `vertices` [V, 3] (world, metres), `up` [3] the capture's up. Each
    direction is a one-view orbit (`render.trajectories.orbit_cameras`: its elevation and azimuth, the bounding
    sphere framed to fill the image)."""
    from dataclasses import replace

    from avatarctl.render.trajectories import OrbitSpec, orbit_cameras

    if distance <= 1.0:
        raise ValueError(f"distance must exceed the bounding sphere's radius (1), got {distance}")
    v = np.asarray(vertices, np.float64)
    centre = 0.5 * (v.min(0) + v.max(0))
    radius = max(float(np.linalg.norm(v - centre, axis=1).max()), 1e-6)
    u = np.asarray(up, np.float64) / np.linalg.norm(up)
    azimuth0 = np.cross(u, [1.0, 0.0, 0.0] if abs(u[0]) < 0.9 else [0.0, 1.0, 0.0])  # horizontal
    golden = np.pi * (3.0 - np.sqrt(5.0))
    cams = []
    for i in range(count):
        z = 1.0 - 2.0 * (i + 0.5) / count
        if abs(z) > pole:
            continue
        spec = OrbitSpec(views=1, elevation_deg=float(np.degrees(np.arcsin(z))), resolution=size, fill=1.0,
                         start_azimuth_deg=float(np.degrees(i * golden)))
        (cam,) = orbit_cameras(spec, centre[None], radius, u, distance * radius, reference_dir=azimuth0)
        cams.append(replace(cam, name=f"around{i:03d}"))
    return cams


def view_colours(vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray, render: ViewRenderFn,
                 cameras: list[Camera], power: float = POWER, min_alpha: float = MIN_ALPHA) -> ViewColours:
    """Steps 2-4 of the module docstring for the mesh (vertices [V, 3], faces [F, 3], normals [V, 3] outward) seen
    by `cameras` (`surround_cameras`), the field's images from `render`."""
    from scipy.spatial import cKDTree

    from avatarctl.geometry.raycast import RayCaster

    V = vertices.shape[0]
    total = np.zeros((V, 3))
    weight = np.zeros(V)
    caster = RayCaster(vertices, faces)
    v = vertices.astype(np.float64)
    face_normal = normals[faces].astype(np.float64).sum(1)
    face_normal /= np.maximum(np.linalg.norm(face_normal, axis=1, keepdims=True), 1e-12)
    for cam in cameras:
        rgb, alpha = render(cam)
        hits = cast_pixels(caster, cam)
        a = alpha.reshape(-1)[hits.pixel].astype(np.float64)
        use = a >= min_alpha
        if not use.any():
            continue
        pixel, face, points, a = hits.pixel[use], hits.face[use], hits.points[use], a[use]
        colour = np.clip(rgb.reshape(-1, 3)[pixel] / a[:, None], 0.0, 1.0)
        ray = points - cam.center[None]
        ray /= np.maximum(np.linalg.norm(ray, axis=1, keepdims=True), 1e-12)
        cos = np.clip(-(face_normal[face] * ray).sum(1), 0.0, 1.0)
        tri = faces[face]
        bc = np.clip(barycentric(points, v[tri[:, 0]], v[tri[:, 1]], v[tri[:, 2]]), 0.0, 1.0)
        w = bc * (cos ** power)[:, None]  # [pixels, 3]
        idx = tri.ravel()
        np.add.at(weight, idx, w.ravel())
        np.add.at(total, idx, (w[..., None] * colour[:, None, :]).reshape(-1, 3))
    seen = weight > 0
    colours = np.zeros((V, 3), np.float32)
    colours[seen] = total[seen] / weight[seen, None]
    if seen.any() and not seen.all():
        _, nearest = cKDTree(v[seen]).query(v[~seen])
        colours[~seen] = colours[seen][nearest]
    return ViewColours(colours=np.clip(colours, 0.0, 1.0), seen=seen, views=len(cameras))


def view_colouring(render: ViewRenderFn, up: np.ndarray, count: int = VIEW_COUNT, size: int = VIEW_SIZE
                   ) -> "VertexColourFn":
    """The whole of it as a `mesh.VertexColourFn` (every vertex coloured at once, whatever is asked for): cameras
    around each mesh it is given (`surround_cameras`), its colours from `render`'s images (`view_colours`)."""

    def colour(vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray, which: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
        cams = surround_cameras(vertices, up, count, size)
        return view_colours(vertices, faces, normals, render, cams).colours, np.ones(vertices.shape[0], bool)

    return colour


# ---- adapter for a fitted Gaussian-field SlrfAvatar ---------------------------------------------------------------
def gaussian_views(model: "SlrfAvatar", state: "NodeState", slot: int = 0) -> ViewRenderFn:
    """The rasterized image (`splat.rasterization`, over black) of frame `slot` of `state`, posed once."""
    import torch

    from avatarctl.splat import SplatCamera, rasterization

    with torch.no_grad():
        posed = model.posed_gaussians(state)
    means, covars = posed.means[slot].float(), posed.covars[slot].float()
    opacities = posed.opacities[slot].float()
    black = torch.zeros(3, device=means.device)

    def render(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
        sc = SplatCamera.from_camera(camera, device=means.device)
        with torch.no_grad():
            rgb, alpha, _ = rasterization(means, covars, posed.colors(slot, sc.center).float(), opacities, [sc], black,
                                          low_pass=model.cfg.gaussians.low_pass)
        return rgb[0].float().cpu().numpy(), alpha[0].float().cpu().numpy()

    return render
