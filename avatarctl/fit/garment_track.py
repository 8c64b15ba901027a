"""Garment registration before the fit: a surface of the loose garment tracked frame by frame through the training
views (issue 48; a deviation from the paper, docs/fit.md "Garment tracking"). No learned weights.

The paper moves every node with the skeleton plus a learned residual Δn (Eq. 3); a skirt's cloth does not follow
the skeleton, and a jointly optimised model does not discover where it goes. This module finds it from the images
first, the way the garment methods of the field do (sequential, warm-started, appearance frozen, physical priors):

1. **Reference surface** (`reference_mesh`): at the reference frame (the middle training frame), a tube about the
   body's up axis over the garment's height: the training masks' visual hull (`geometry.hull.carve`, `voxel`
   metres) holds volume farther than `off_body` from the posed body that some view puts on a mask pixel the body's
   own silhouette does not explain (what the body cannot explain: the garment); the tube spans the heights of that
   volume (1st to 99th percentile, plus `tube_top` above it: the waistband that lies on the body), one ring per
   `voxel` of height, `tube_segments` around, each ring centred on the hull's cross-section there, its radius at each
   angle the hull's outer boundary along that direction. Then multi-view stereo (`refine_reference`) moves each
   vertex along its normal to where the views agree on its colour. One closed piece: the tracker's edge lengths and
   silhouette hold it whole (the hull's off-body surface itself covers the cloth in pieces, and loses it; docs/fit.md
   "Garment tracking"). No truth is needed.
2. **Tracking** (`track`): from the reference frame forwards, then backwards, each frame's surface starts from the
   previous one moved by the skeleton (each vertex by the blended transform of its nearest body vertex, Eq. 1) plus
   the previous step's motion beyond the skeleton (constant velocity), each ring of the tube then turned about the up
   axis by its own angle (`twist`: one L-BFGS solve of the angles on the photometric term below at blur 1 px, with
   neighbouring rings turning alike, `twist_smooth`: a swinging skirt turns its lower rings beyond that start), and
   is then solved by L-BFGS over an image pyramid (Gaussian blur `sigmas`, pixels: 1 then 0.5; the start is within a
   few pixels, and a coarser level blurs the print away, whose minimum then pulls a twirling skirt off the cloth)
   for: the colour of each surface sample (vertices and 4 points per triangle) in every training view that saw it at
   the previous frame equal to its colour there (the appearance is the previous frame's images, frozen: only moving
   the surface lowers the loss), plus `anchor` x the same against the reference frame's mean colour of the sample (no
   drift where the reference colour is right); edge lengths kept (`isometry`, the cloth does not stretch),
   neighbouring vertices moving alike (`smooth`), every vertex inside the frame's masks (`silhouette`, squared pixels
   outside). Visibility: a ray from the camera to the vertex hits the body or the surface within 1 cm of it (Warp's
   BVH, `geometry.raycast`), the surface not seen edge-on.
2b. **Rescue** (`rescue`, `track_rescue`): where a direction lost the surface (a twirl flares the hem beyond the tube
   built where the skirt hangs), a second, stiff tube is built at the lost frame where the garment is most spread
   (and at the frames before it: the one whose way back to the last frame tracked lands on the surface held there),
   tracked back to the last frame tracked and forward over the lost ones, with the twist and without (the side keeps
   the one whose carried surfaces the reference colours fit best: each loses the cloth on some captures); the first
   surface follows its motion there (each vertex by the rigid motion of its nearest second-tube vertices), kept on
   the frames where it explains the reference colours better than the skeleton does.
3. **Node motions** (`node_motions`): each node given to track owns its `patch` nearest surface vertices within
   `reach` at the reference frame; per frame, the best rigid motion (Kabsch) of those vertices from the reference
   frame is the node's motion. The fit places the node by it on training frames (`SlrfAvatar.set_tracks`); on
   frames the tracker did not reach, by the skeleton with the offset of the last tracked frame held (`placement`).

Measured on synth small (docs/fit.md "Garment tracking"): the tracked surface against the true cloth.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch

from avatarctl.geometry.align import rigid_align
from avatarctl.geometry.cameras import Camera
from avatarctl.geometry.normals import vertex_normals
from avatarctl.progress import ProgressFn, ProgressReport


@dataclass(frozen=True)
class TrackSettings:
    """The tracker's weights (module docstring, step 2); each term in its own unit, weighted against the photometric
    term (mean squared colour difference x 1e3)."""

    sigmas: tuple[float, ...] = (1.0, 0.5)  # the tracker's image blur per pyramid level, pixels, coarse to fine
    stereo_sigmas: tuple[float, ...] = (4.0, 2.0, 1.0)  # the reference stereo's, pixels, coarse to fine
    iters: int = 30  # L-BFGS iterations per level
    twist: float = 1.0  # the twist pre-solve's image blur, pixels (step 2: one turn about the up axis per ring); 0: off
    twist_smooth: float = 10.0  # (angle_r - angle_r+1)^2 of neighbouring rings, degrees^2 x 0.01, in the pre-solve
    isometry: float = 10.0  # (edge length - reference length)^2, cm^2
    smooth: float = 10.0  # |displacement_i - displacement_j|^2 over edges, cm^2
    silhouette: float = 1.0  # squared pixels outside the frame's mask, per view
    anchor: float = 0.3  # the reference frame's colours, against the previous frame's (1)
    residual_velocity: float = 1.0  # share of the last step's motion beyond the skeleton carried forward
    lost: float = 2.0  # a direction stops where a frame's loss exceeds this x the median of its first 5 frames
    voxel: float = 0.02  # the reference surface's hull grid, metres
    stereo_iters: int = 60  # L-BFGS iterations per level of the reference surface's multi-view stereo
    stereo_smooth: float = 3.0  # (offset_i - offset_j)^2 over edges, cm^2, in the stereo
    stereo_reach: float = 0.1  # the stereo moves a vertex at most this far (metres) along its normal
    off_body: float = 0.02  # hull volume this far (metres) from the posed body may be garment
    explain_px: int = 2  # the body's silhouette grown by this many pixels before it explains a mask pixel
    tube_top: float = 0.08  # the tube reaches this far (metres) above the garment's off-body volume
    tube_segments: int = 72  # tube vertices around each ring
    rescue_min_frames: int = 3  # step 2b on a side of the reference with at least this many frames lost
    rescue_isometry: float = 100.0  # the second surface's `isometry` (step 2b: a tube where the cloth is spread)
    rescue_smooth: float = 1.0  # its `smooth`
    rescue_k: int = 10  # the second surface's vertices whose rigid motion carries each first-surface vertex
    rescue_candidates: int = 3  # second surfaces tried: at the spread frame and the frames before it (step 2b)


@dataclass(frozen=True)
class GarmentMesh:
    """The tracked surface at the reference frame."""

    vertices: np.ndarray  # [V, 3] world metres
    faces: np.ndarray  # [T, 3] int
    frame: int  # capture frame id of the reference frame
    segments: int = 0  # a tube's vertices per ring (vertex r * segments + k, rings from the hem up); 0: not a tube

    def __post_init__(self) -> None:
        assert self.vertices.ndim == 2 and self.vertices.shape[1] == 3, f"vertices {self.vertices.shape}"
        assert self.faces.ndim == 2 and self.faces.shape[1] == 3, f"faces {self.faces.shape}"
        assert self.segments >= 0 and (not self.segments or len(self.vertices) % self.segments == 0), \
            f"{len(self.vertices)} vertices are no rings of {self.segments}"

    @property
    def edges(self) -> np.ndarray:
        """[E, 2] unique undirected edges of the faces."""
        f = self.faces
        e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), 1)
        return np.unique(e, axis=0)


@dataclass(frozen=True)
class TrackingInput:
    """What the tracker reads of a capture: the training views and the posed body of each frame to track."""

    frames: tuple[int, ...]  # capture frame ids, in time order
    cameras: tuple[Camera, ...]  # the undistorted (pinhole) training views
    image: Callable[[int, int], np.ndarray]  # (view index, frame id) -> RGB uint8 [H, W, 3]
    mask: Callable[[int, int], np.ndarray]  # (view index, frame id) -> bool [H, W]
    body_vertices: np.ndarray  # [F, Vb, 3] posed body per frame (the order of `frames`), world metres
    body_faces: np.ndarray  # [Tb, 3]
    body_transforms: Callable[[int, np.ndarray], np.ndarray]  # (frame index, body vertex ids [n]) -> [n, 4, 4] Eq. 1
    up: np.ndarray  # [F, 3] unit vectors: the body's up axis per frame (the rest pose's head direction, posed)

    def __post_init__(self) -> None:
        F = len(self.frames)
        assert self.body_vertices.shape[0] == F, f"body_vertices {self.body_vertices.shape} for {F} frames"
        assert self.up.shape == (F, 3), f"up {self.up.shape} for {F} frames"
        assert len(self.cameras) >= 1

    @property
    def projections(self) -> np.ndarray:
        """[C, 3, 4] K [R | T]."""
        from avatarctl.geometry.triangulate import projection_matrices

        return projection_matrices(self.cameras)

    @property
    def centers(self) -> np.ndarray:
        """[C, 3] camera centres, world metres."""
        return np.stack([c.center for c in self.cameras])


@dataclass(frozen=True)
class GarmentTracks:
    """The tracked surface over the frames of a `TrackingInput`."""

    mesh: GarmentMesh
    frames: tuple[int, ...]  # capture frame ids
    vertices: np.ndarray  # [F, V, 3] world metres
    seen: np.ndarray  # [F, V] int: training views that saw each vertex (at the frame it was tracked from)
    loss: np.ndarray  # [F] photometric loss after tracking (0 at the reference frame)
    tracked: np.ndarray  # [F] bool: the frames the surface was followed to (`track`'s stop rule ends a direction;
    # `rescue` adds lost frames it found the surface on)
    seconds: float = 0.0

    def __post_init__(self) -> None:
        F, V = len(self.frames), self.mesh.vertices.shape[0]
        assert self.vertices.shape == (F, V, 3), f"vertices {self.vertices.shape}, want ({F}, {V}, 3)"
        assert self.seen.shape == (F, V) and self.loss.shape == (F,) and self.tracked.shape == (F,)


@dataclass(frozen=True)
class NodeMotions:
    """Per training frame, the rigid motion of each tracked node's surface patch from the reference frame."""

    nodes: np.ndarray  # [M] node indices (of the model) that own a patch
    rotation: np.ndarray  # [F, M, 3, 3]
    translation: np.ndarray  # [F, M, 3] x_f = R x_ref + t
    vertices: np.ndarray  # [M] surface vertices in each patch
    seen: np.ndarray  # [F, M] share of the patch's vertices seen by two views or more


# ---- 1. reference surface ---------------------------------------------------------------------------------------
def tube_faces(rings: int, segments: int) -> np.ndarray:
    """[2 (rings - 1) segments, 3] int64 triangles of a tube whose vertices are `rings` rings of `segments`, ring by
    ring (vertex r * segments + k), each ring closed."""
    i, j = np.meshgrid(np.arange(rings - 1), np.arange(segments), indexing="ij")
    a, b = (i * segments + j).ravel(), (i * segments + (j + 1) % segments).ravel()
    return np.concatenate([np.stack([a, a + segments, b], 1), np.stack([b, a + segments, b + segments], 1)]
                          ).astype(np.int64)


def body_explains(inp: TrackingInput, fi: int, settings: TrackSettings = TrackSettings()) -> list[np.ndarray]:
    """Per training view, bool [H, W]: the mask pixels the posed body explains at frame index `fi` (its silhouette
    grown by `explain_px`); the rest of a mask is the garment's, or the masks' error."""
    import cv2

    from avatarctl.geometry.silhouette import rasterize_silhouette

    grow = np.ones((2 * settings.explain_px + 1,) * 2, dtype=np.uint8)
    body = inp.body_vertices[fi].astype(np.float64)
    return [cv2.dilate(rasterize_silhouette(c, body, inp.body_faces, supersample=1).astype(np.uint8), grow) > 0
            for c in inp.cameras]


def reference_mesh(inp: TrackingInput, ref: int, settings: TrackSettings = TrackSettings()) -> GarmentMesh:
    """Step 1 of the module docstring at frame index `ref` of `inp` (before the stereo). An empty mesh when nothing
    is off the body."""
    from scipy.ndimage import gaussian_filter, gaussian_filter1d, map_coordinates
    from scipy.spatial import cKDTree

    from avatarctl.geometry.hull import carve

    frame = inp.frames[ref]
    body = inp.body_vertices[ref].astype(np.float64)
    up = inp.up[ref] / np.linalg.norm(inp.up[ref])
    cams = list(inp.cameras)
    masks = [inp.mask(c, frame) for c in range(len(cams))]
    vox = settings.voxel
    lo, hi = body.min(0) - 0.35, body.max(0) + 0.35
    empty = GarmentMesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64), frame)
    explained = body_explains(inp, ref, settings)
    off = carve(cams, masks, lo, hi, vox, explained=explained)  # [M, 3] voxel centres no body explains
    off = off[cKDTree(body).query(off)[0] > settings.off_body] if len(off) else off
    if len(off) < 8:
        return empty
    hull = carve(cams, masks, lo, hi, vox)
    shape = tuple(int(round((b - a) / vox)) for a, b in zip(lo, hi))
    grid = np.zeros(shape, dtype=np.float32)
    idx = np.floor((hull - lo) / vox).astype(np.int64)
    grid[tuple(idx[((idx >= 0) & (idx < np.array(shape))).all(1)].T)] = 1.0
    grid = gaussian_filter(grid, 1.0)
    # the rings: heights along up, each centred on the hull's cross-section near the body there
    h_off = off @ up
    heights = np.arange(np.percentile(h_off, 1), np.percentile(h_off, 99) + settings.tube_top + 1e-9, vox)
    band = body[(body @ up >= heights[0]) & (body @ up <= heights[-1])]
    axis = np.median(band if len(band) else body, 0)
    axis -= (axis @ up) * up  # a point of the body's axis, in the plane through the origin normal to up
    centres = []
    for h in heights:
        near = hull[np.abs(hull @ up - h) < 1.5 * vox]
        flat = near - (near @ up)[:, None] * up
        near = near[np.linalg.norm(flat - axis, axis=1) < 0.5]
        c = np.median(near, 0) if len(near) else axis
        centres.append(c - (c @ up) * up)
    centres = gaussian_filter1d(np.stack(centres), 1.5, axis=0, mode="nearest")  # [H, 3]
    e1 = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    angles = np.arange(settings.tube_segments) * 2 * np.pi / settings.tube_segments
    ray = np.cos(angles)[:, None] * e1 + np.sin(angles)[:, None] * e2  # [A, 3]
    radii = np.arange(0.9, 0.0, -vox / 4)  # from outside inwards: the first voxel inside is the outer boundary
    X = (centres[:, None, None] + heights[:, None, None, None] * up + radii[None, None, :, None] * ray[None, :, None])
    occupied = map_coordinates(grid, ((X.reshape(-1, 3) - lo) / vox - 0.5).T, order=1, mode="constant",
                               cval=0.0).reshape(X.shape[:3]) > 0.5  # [H, A, R]
    hit = occupied.any(-1)
    if hit.mean() < 0.5:
        return empty
    R = radii[np.argmax(occupied, -1)]  # [H, A]
    ring = np.array([np.median(r[k]) if k.any() else np.median(R[hit]) for r, k in zip(R, hit)])
    R = np.where(hit, R, ring[:, None])  # a ray through a gap: the ring's median
    R = gaussian_filter(R, 0.7, mode=("nearest", "wrap"))
    verts = (centres[:, None] + heights[:, None, None] * up + R[..., None] * ray[None]).reshape(-1, 3)
    A = settings.tube_segments
    faces = tube_faces(len(heights), A)
    outward = verts - np.repeat(centres, A, 0) - (verts @ up)[:, None] * up
    if (np.einsum("vi,vi->v", vertex_normals(verts, faces), outward) < 0).mean() > 0.5:
        faces = faces[:, [0, 2, 1]]
    return GarmentMesh(vertices=verts, faces=faces, frame=frame, segments=A)


# ---- 2. tracking ------------------------------------------------------------------------------------------------
_BARY = torch.tensor([[1 / 3, 1 / 3, 1 / 3], [2 / 3, 1 / 6, 1 / 6], [1 / 6, 2 / 3, 1 / 6], [1 / 6, 1 / 6, 2 / 3]])


class _Frames:
    """The blurred colour images [C, 3, H, W] and outside-mask distance maps [C, 1, H, W] of frames, cached. With
    `noise_background`, each view's pixels outside its mask are random colours (a uniform background is not a place
    where the views agree)."""

    def __init__(self, inp: TrackingInput, noise_background: bool = False, device: str | torch.device = "cpu"):
        self.inp, self.noise_background, self.device = inp, noise_background, torch.device(device)
        self.rgb: dict[tuple[int, float], torch.Tensor] = {}
        self.dt: dict[int, torch.Tensor] = {}

    def colour(self, frame: int, sigma: float) -> torch.Tensor:
        import cv2

        key = (frame, sigma)
        if key not in self.rgb:
            ims = []
            for c in range(len(self.inp.centers)):
                im = self.inp.image(c, frame).astype(np.float32) / 255.0
                if self.noise_background:
                    out = ~self.inp.mask(c, frame)
                    im[out] = np.random.default_rng(c).random((int(out.sum()), 3), dtype=np.float32)
                ims.append(cv2.GaussianBlur(im, (0, 0), sigma) if sigma > 0 else im)
            self.rgb[key] = torch.as_tensor(np.stack(ims)).permute(0, 3, 1, 2).contiguous().to(self.device)
        return self.rgb[key]

    def outside(self, frame: int) -> torch.Tensor:
        import cv2

        if frame not in self.dt:
            d = [cv2.distanceTransform((~self.inp.mask(c, frame)).astype(np.uint8), cv2.DIST_L2, 3)
                 for c in range(len(self.inp.centers))]
            self.dt[frame] = torch.as_tensor(np.stack(d))[:, None].float().to(self.device)
        return self.dt[frame]

    def forget(self, keep: set[int]) -> None:
        self.rgb = {k: v for k, v in self.rgb.items() if k[0] in keep}
        self.dt = {k: v for k, v in self.dt.items() if k in keep}


def _project(P: torch.Tensor, X: torch.Tensor) -> torch.Tensor:
    """X [n, 3] -> pixels [C, n, 2] through P [C, 3, 4]."""
    x = torch.einsum("cij,nj->cni", P[..., :3], X) + P[:, None, :, 3]
    return x[..., :2] / x[..., 2:3].clamp(min=1e-6)


def _sample(img: torch.Tensor, px: torch.Tensor) -> torch.Tensor:
    """img [C, K, H, W], px [C, n, 2] pixels -> [C, n, K] bilinear, zeros outside."""
    H, W = img.shape[-2:]
    g = torch.stack([px[..., 0] / (W - 1) * 2 - 1, px[..., 1] / (H - 1) * 2 - 1], -1)
    return torch.nn.functional.grid_sample(img, g[:, None], align_corners=True)[:, :, 0].transpose(1, 2)


def _samples(X: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """The photometric samples: vertices, then 4 barycentric points per triangle -> [V + 4 T, 3]."""
    return torch.cat([X, torch.einsum("bk,tkd->tbd", _BARY.to(X), X[faces]).reshape(-1, 3)])


def visibility(inp: TrackingInput, fi: int, X: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """[C, V] bool: vertex X_v seen by training view c at frame index `fi` (module docstring, step 2)."""
    from avatarctl.geometry.raycast import RayCaster, seen_by

    body = inp.body_vertices[fi]
    caster = RayCaster(np.concatenate([body, X]), np.concatenate([inp.body_faces, faces + len(body)]))
    return seen_by(caster, inp.centers, X, vertex_normals(X, faces), min_cos=0.25, two_sided=True)


def skin_move(inp: TrackingInput, X: np.ndarray, fa: int, fb: int) -> np.ndarray:
    """X [n, 3] at frame index fa moved to frame index fb by the blended transform of its nearest body vertex."""
    from scipy.spatial import cKDTree

    _, j = cKDTree(inp.body_vertices[fa]).query(X)
    M = inp.body_transforms(fb, j) @ np.linalg.inv(inp.body_transforms(fa, j))  # [n, 4, 4]
    return (M[:, :3, :3] @ X[..., None])[..., 0] + M[:, :3, 3]


class _Tracker:
    def __init__(self, inp: TrackingInput, mesh: GarmentMesh, ref: int, settings: TrackSettings,
                 device: str | torch.device = "cpu"):
        self.inp, self.s, self.ref, self.dev = inp, settings, ref, torch.device(device)
        self.frames = _Frames(inp, device=self.dev)
        self.P = torch.as_tensor(inp.projections, dtype=torch.float32, device=self.dev)
        self.faces = torch.as_tensor(mesh.faces, device=self.dev)
        self.edges = torch.as_tensor(mesh.edges, device=self.dev)
        X0 = torch.as_tensor(mesh.vertices, dtype=torch.float32, device=self.dev)
        self.rest = (X0[self.edges[:, 0]] - X0[self.edges[:, 1]]).norm(dim=-1)
        self.faces_np, self.segments = mesh.faces, mesh.segments
        # the reference colours: per sample, the mean over the views that see it at the reference frame
        vis = torch.as_tensor(visibility(inp, ref, mesh.vertices, mesh.faces), device=self.dev).float()  # [C, V]
        self.tex = {}
        svis = self._sample_vis(vis)
        for sigma in settings.sigmas:
            c = _sample(self.frames.colour(inp.frames[ref], sigma), _project(self.P, _samples(X0, self.faces)))
            k = svis.sum(0)  # [S]
            self.tex[sigma] = ((svis[..., None] * c).sum(0) / k.clamp(min=1)[:, None], (k > 0).float())

    def _sample_vis(self, vis: torch.Tensor) -> torch.Tensor:
        """[C, V] vertex visibility -> [C, S] sample visibility (a triangle's points: all three vertices seen)."""
        tri = (vis[:, self.faces].min(-1).values > 0).float()  # [C, T]
        return torch.cat([vis, tri.repeat_interleave(len(_BARY), 1)], 1)

    def twist(self, init: np.ndarray, Xp: torch.Tensor, svis: torch.Tensor, fa: int, fb: int) -> np.ndarray:
        """Step 2's pre-solve: the tube at `init` [V, 3] with each ring turned about the up axis (frame index fb's)
        through its centre by one angle, the angles found by L-BFGS on the photometric term (blur `twist` px) and
        `twist_smooth`; -> the turned vertices [V, 3], where the full solve starts. A swinging skirt turns its lower
        rings beyond where the skeleton and the last step's velocity put them; one angle a ring follows the print
        that far without the freedom that lets a blurred print pull single vertices off the cloth."""
        s, inp = self.s, self.inp
        X0 = torch.as_tensor(init, dtype=torch.float32, device=self.dev)
        rings = X0.reshape(-1, self.segments, 3)
        centre = rings.mean(1, keepdim=True)
        up = torch.as_tensor(inp.up[fb] / np.linalg.norm(inp.up[fb]), dtype=torch.float32, device=self.dev)
        q = rings - centre
        along = (q @ up)[..., None] * up
        p = q - along  # [R, A, 3] each vertex's offset from its ring's centre, normal to up
        p90 = torch.cross(up.expand_as(p), p, dim=-1)  # p turned by 90 degrees about up
        angle = torch.zeros(len(rings), device=self.dev, requires_grad=True)
        before = _sample(self.frames.colour(inp.frames[fa], s.twist), _project(self.P, _samples(Xp, self.faces)))
        after = self.frames.colour(inp.frames[fb], s.twist)
        n = svis.sum().clamp(min=1)
        opt = torch.optim.LBFGS([angle], lr=1, max_iter=s.iters, line_search_fn="strong_wolfe")

        def turned() -> torch.Tensor:
            a = angle[:, None, None]
            return (centre + along + torch.cos(a) * p + torch.sin(a) * p90).reshape(-1, 3)

        def closure():
            opt.zero_grad()
            c = _sample(after, _project(self.P, _samples(turned(), self.faces)))
            degrees = torch.rad2deg(angle)
            loss = ((svis * ((c - before) ** 2).sum(-1)).sum() / n * 1e3 +
                    s.twist_smooth * ((degrees[1:] - degrees[:-1]) ** 2).mean() * 1e-2)
            loss.backward()
            return loss

        opt.step(closure)
        return turned().detach().cpu().numpy().astype(np.float64)

    def explains(self, X: np.ndarray, fi: int) -> float:
        """How far the reference frame's colours of the surface samples are from frame index `fi`'s images with the
        surface at X (the mean squared difference over the samples the views see there, blur `sigmas[1]`)."""
        sigma = self.s.sigmas[min(1, len(self.s.sigmas) - 1)]
        svis = self._sample_vis(torch.as_tensor(visibility(self.inp, fi, X, self.faces_np), device=self.dev).float())
        tex, has = self.tex[sigma]
        with torch.no_grad():
            c = _sample(self.frames.colour(self.inp.frames[fi], sigma),
                        _project(self.P, _samples(torch.as_tensor(X, dtype=torch.float32, device=self.dev),
                                                  self.faces)))
        w = svis * has
        return float((w * ((c - tex) ** 2).sum(-1)).sum() / w.sum().clamp(min=1))

    def step(self, Xp: np.ndarray, Xpp: np.ndarray | None, fa: int, fb: int, init: np.ndarray | None = None
             ) -> tuple[np.ndarray, np.ndarray, float]:
        """Frame index fa -> fb (adjacent): -> (vertices [V, 3], views seeing each vertex at fa [V], loss). `init`:
        the solve's start [V, 3] (default: Xp moved by the skeleton and the constant velocity)."""
        s, inp = self.s, self.inp
        vis_np = visibility(inp, fa, Xp, self.faces_np)
        svis = self._sample_vis(torch.as_tensor(vis_np, device=self.dev).float())
        if init is None:
            init = skin_move(inp, Xp, fa, fb)
            if Xpp is not None and s.residual_velocity:
                init = init + s.residual_velocity * (Xp - skin_move(inp, Xpp, 2 * fa - fb, fa))
        Xp_t = torch.as_tensor(Xp, dtype=torch.float32, device=self.dev)
        if s.twist and self.segments:
            init = self.twist(init, Xp_t, svis, fa, fb)
        X = torch.as_tensor(init, dtype=torch.float32, device=self.dev).clone().requires_grad_(True)
        e0, e1 = self.edges[:, 0], self.edges[:, 1]
        dt = self.frames.outside(inp.frames[fb])
        w = svis
        n = w.sum().clamp(min=1)
        V = len(Xp)
        loss_value = 0.0
        Sp = _samples(Xp_t, self.faces)
        for sigma in s.sigmas:
            A, B = self.frames.colour(inp.frames[fa], sigma), self.frames.colour(inp.frames[fb], sigma)
            c0 = _sample(A, _project(self.P, Sp))  # [C, S, 3] the previous frame's colours, frozen
            tex, has = self.tex[sigma]
            opt = torch.optim.LBFGS([X], lr=1, max_iter=s.iters, line_search_fn="strong_wolfe")

            def closure():
                opt.zero_grad()
                px = _project(self.P, _samples(X, self.faces))  # [C, S, 2]
                c1 = _sample(B, px)
                data = (w * ((c1 - c0) ** 2).sum(-1)).sum() / n * 1e3
                anchor = (w * has * ((c1 - tex) ** 2).sum(-1)).sum() / n * 1e3
                L = (X[e0] - X[e1]).norm(dim=-1)
                iso = ((L - self.rest) ** 2).mean() * 1e4
                d = X - Xp_t
                smooth = ((d[e0] - d[e1]) ** 2).sum(-1).mean() * 1e4
                sil = (_sample(dt, px[:, :V])[..., 0] ** 2).mean(1).sum()
                loss = data + s.anchor * anchor + s.isometry * iso + s.smooth * smooth + s.silhouette * sil
                loss.backward()
                return loss

            loss_value = float(opt.step(closure).detach())
        return X.detach().cpu().numpy().astype(np.float64), vis_np.sum(0), loss_value


def track(inp: TrackingInput, mesh: GarmentMesh, ref: int, settings: TrackSettings = TrackSettings(),
          progress: ProgressFn | None = None, done: GarmentTracks | None = None, stop: bool = True,
          device: str | torch.device = "cpu") -> GarmentTracks:
    """Step 2 of the module docstring: the surface `mesh` (at frame index `ref`) through every frame of `inp`, each
    direction until the surface is lost: where the reference colours fit the frame no better with the tracked surface
    than with the reference surface moved by the skeleton alone (`_Tracker.explains`), or the frame's loss exceeds
    `settings.lost` x the median of the direction's first five (a fast twirl); the frames from there on are not
    tracked (the fit places their nodes by the skeleton). `done`: a partial result of the same input to continue
    (its tracked frames are kept). `stop=False`: no stop rule, every frame tracked (benchmarks.garment_tracking's
    `--through`: how the surface is lost). `device`: where the photometric solve runs (the visibility rays: CPU)."""
    import time

    t0 = time.perf_counter()
    F, V = len(inp.frames), len(mesh.vertices)
    out = np.zeros((F, V, 3))
    seen = np.zeros((F, V), dtype=np.int64)
    loss = np.zeros(F)
    have = np.zeros(F, dtype=bool)
    out[ref] = mesh.vertices
    have[ref] = True
    if done is not None:
        have = done.tracked.copy()
        have[ref] = True
        out[have], seen[have], loss[have] = done.vertices[have], done.seen[have], done.loss[have]
    tracker = _Tracker(inp, mesh, ref, settings, device)
    tracked = have.copy()
    count = 0
    for direction in (1, -1):
        prev2, prev, f, first = None, ref, ref + direction, []
        while 0 <= f < F:
            if not have[f]:
                Xpp = out[prev2] if prev2 is not None else None
                out[f], seen[f], loss[f] = tracker.step(out[prev], Xpp, prev, f)
                tracker.frames.forget({inp.frames[prev], inp.frames[f], inp.frames[ref]})
            skeleton = skin_move(inp, mesh.vertices, ref, f) if stop else None
            if stop and ((len(first) >= 5 and loss[f] > settings.lost * np.median(first)) or
                         tracker.explains(out[f], f) >= tracker.explains(skeleton, f)):
                out[f], seen[f] = 0.0, 0
                break  # lost: this frame and the ones after it keep the skeleton's placement
            first = first if len(first) >= 5 else first + [loss[f]]
            tracked[f] = True
            count += 1
            if progress is not None:
                progress(ProgressReport(done=count, total=F - 1, part="track"))
            prev2, prev, f = prev, f, f + direction
    seen[ref] = visibility(inp, ref, mesh.vertices, mesh.faces).sum(0)
    return GarmentTracks(mesh=mesh, frames=tuple(inp.frames), vertices=out, seen=seen, loss=loss, tracked=tracked,
                         seconds=time.perf_counter() - t0)


# ---- 2b. rescue ----------------------------------------------------------------------------------------------
def spread_frame(inp: TrackingInput, frames: list[int], settings: TrackSettings = TrackSettings()) -> int:
    """The frame index among `frames` (consecutive, in time order) where the garment is most spread: the most mask
    pixels over the views that the body's silhouette (grown by `explain_px`) does not explain, each frame's count
    the least of its own and its neighbours' in `frames` (one odd mask does not choose)."""
    count = np.asarray([sum(int((inp.mask(c, inp.frames[fi]) & ~e).sum())
                            for c, e in enumerate(body_explains(inp, fi, settings))) for fi in frames])
    low = np.minimum(count, np.minimum(np.r_[count[:1], count[:-1]], np.r_[count[1:], count[-1:]]))
    return frames[int(np.argmax(low))]


def carry(X: np.ndarray, Y0: np.ndarray, Y: np.ndarray, k: int) -> np.ndarray:
    """X [n, 3] moved as the surface Y0 [m, 3] moves to Y [m, 3]: each point by the rigid motion (Kabsch) of its k
    nearest points of Y0."""
    from scipy.spatial import cKDTree

    _, j = cKDTree(Y0).query(X, k=min(k, len(Y0)))
    j = j.reshape(len(X), -1)
    R, t = rigid_align(Y0[j], Y[j])  # [n, 3, 3], [n, 3]
    return (R @ X[..., None])[..., 0] + t


def _chamfer(A: np.ndarray, B: np.ndarray) -> float:
    """Mean distance (metres) of A's points [n, 3] to B's nearest and of B's [m, 3] to A's, averaged."""
    from scipy.spatial import cKDTree

    return 0.5 * float(cKDTree(B).query(A)[0].mean() + cKDTree(A).query(B)[0].mean())


def rescue(inp: TrackingInput, tracks: GarmentTracks, ref: int, settings: TrackSettings = TrackSettings(),
           progress: ProgressFn | None = None, device: str | torch.device = "cpu") -> GarmentTracks:
    """Step 2b of the module docstring: on each side of the reference frame where `track` lost the surface on
    `rescue_min_frames` frames or more, a second tube built (step 1; stiff: `rescue_isometry`, `rescue_smooth`) at
    the frame where the garment is most spread among the lost ones (`spread_frame`) and at each of the
    `rescue_candidates` - 1 frames before it, each tracked back to the last frame tracked; the one that arrives
    nearest the tracked surface there (`_chamfer`: the way back held the cloth) is tracked from there forward over
    the lost frames (its first step starting where the way back found it). All of it twice where `twist` is on:
    with the twist pre-solve and without; the side keeps the pass whose carried surfaces (below) the reference
    colours fit best summed over its lost frames (synth small: the twist's pass lost the cloth on seed 1, the plain
    one drifted on seed 0). The tracked surface carried from that last frame by the second tube's motion (`carry`)
    is kept on each lost frame where the reference colours fit the frame better than with the surface moved by the
    skeleton from that frame (the placement the fit would hold there). -> the tracks with those frames tracked."""
    import time
    from dataclasses import replace

    t0 = time.perf_counter()
    F = len(inp.frames)
    out, seen, tracked = tracks.vertices.copy(), tracks.seen.copy(), tracks.tracked.copy()
    stiff = replace(settings, isometry=settings.rescue_isometry, smooth=settings.rescue_smooth)
    first = None
    sides = [[f for f in range(ref + d, F if d > 0 else -1, d) if not tracked[f]] for d in (1, -1)]
    # tracked with the twist pre-solve and without (each loses the cloth on some captures): a side keeps the one whose
    # carried surfaces the reference colours fit best over its lost frames
    variants = [stiff, replace(stiff, twist=0.0)] if stiff.twist else [stiff]
    total = sum(len(lost) + settings.rescue_candidates for lost in sides
                if len(lost) >= settings.rescue_min_frames) * len(variants)
    count = 0
    for d, lost in zip((1, -1), sides):
        if len(lost) < settings.rescue_min_frames:
            continue
        s = lost[0] - d  # the last frame tracked on this side (a direction stops at its first lost frame)
        r = spread_frame(inp, sorted(lost), settings)
        options, built = [], {}
        for variant in variants:
            best = None
            for c in [r - k * d for k in range(settings.rescue_candidates) if (r - k * d - s) * d > 0]:
                if c not in built:  # the second tube does not depend on the twist
                    built[c] = refine_reference(inp, reference_mesh(inp, c, stiff), c, stiff, device)
                second = built[c]
                if len(second.vertices) < 20:
                    continue
                tracker = _Tracker(inp, second, c, variant, device)
                back = {c: second.vertices}
                for f in range(c - d, s - d, -d):  # c -> s
                    back[f] = tracker.step(back[f + d], back.get(f + 2 * d), f + d, f)[0]
                    tracker.frames.forget({inp.frames[f], inp.frames[f + d], inp.frames[c]})
                gap = _chamfer(back[s], out[s])
                if best is None or gap < best[0]:
                    best = (gap, tracker, back)
                count += 1
                if progress is not None:
                    progress(ProgressReport(done=count, total=total, part="rescue"))
            if best is None:
                continue
            _, tracker, back = best
            Y = {s: back[s]}
            for f in lost:  # s -> the side's last frame
                Y[f] = tracker.step(Y[f - d], Y.get(f - 2 * d), f - d, f, init=back.get(f) if f - d == s else None)[0]
                tracker.frames.forget({inp.frames[f], inp.frames[f - d], inp.frames[tracker.ref]})
                count += 1
                if progress is not None:
                    progress(ProgressReport(done=count, total=total, part="rescue"))
            options.append(Y)
        if not options:
            continue
        if first is None:
            first = _Tracker(inp, tracks.mesh, ref, settings, device)
        carried = [{f: carry(out[s], Y[s], Y[f], settings.rescue_k) for f in lost} for Y in options]
        fits = [{f: first.explains(X, f) for f, X in C.items()} for C in carried]
        pick = min(range(len(carried)), key=lambda i: sum(fits[i].values()))  # over the side
        for f in lost:
            if fits[pick][f] < first.explains(skin_move(inp, out[s], s, f), f):
                out[f], tracked[f] = carried[pick][f], True
                seen[f] = visibility(inp, f, carried[pick][f], tracks.mesh.faces).sum(0)
    return GarmentTracks(mesh=tracks.mesh, frames=tracks.frames, vertices=out, seen=seen, loss=tracks.loss,
                         tracked=tracked, seconds=tracks.seconds + time.perf_counter() - t0)


def refine_reference(inp: TrackingInput, mesh: GarmentMesh, ref: int, settings: TrackSettings = TrackSettings(),
                     device: str | torch.device = "cpu") -> GarmentMesh:
    """Multi-view stereo of the reference surface (step 1 of the module docstring): the visual hull lies outside the
    cloth (by centimetres with 8 views), so each vertex is moved along its normal to where the training views agree
    on the colour of the surface samples (the variance over the views that see a sample), with neighbouring offsets
    alike (`stereo_smooth`) and every vertex inside the masks; coarse to fine over `stereo_sigmas`."""
    if not len(mesh.vertices):
        return mesh
    dev = torch.device(device)
    frames = _Frames(inp, noise_background=True, device=dev)
    P = torch.as_tensor(inp.projections, dtype=torch.float32, device=dev)
    faces = torch.as_tensor(mesh.faces, device=dev)
    edges = torch.as_tensor(mesh.edges, device=dev)
    X0 = torch.as_tensor(mesh.vertices, dtype=torch.float32, device=dev)
    n = torch.as_tensor(vertex_normals(mesh.vertices, mesh.faces), dtype=torch.float32, device=dev)
    offset = torch.zeros(len(X0), requires_grad=True, device=dev)
    dt = frames.outside(inp.frames[ref])
    reach = settings.stereo_reach
    for sigma in settings.stereo_sigmas:
        X = (X0 + offset.detach()[:, None] * n).cpu().numpy().astype(np.float64)
        vis = torch.as_tensor(visibility(inp, ref, X, mesh.faces), device=dev).float()
        tri = (vis[:, faces].min(-1).values > 0).float()
        svis = torch.cat([vis, tri.repeat_interleave(len(_BARY), 1)], 1)  # [C, S]
        k = svis.sum(0)
        use = (k >= 2).float()
        img = frames.colour(inp.frames[ref], sigma)
        opt = torch.optim.LBFGS([offset], lr=1, max_iter=settings.stereo_iters, line_search_fn="strong_wolfe")

        def closure():
            opt.zero_grad()
            o = reach * torch.tanh(offset / reach)
            Xc = X0 + o[:, None] * n
            px = _project(P, _samples(Xc, faces))
            c = _sample(img, px)  # [C, S, 3]
            mean = (svis[..., None] * c).sum(0) / k.clamp(min=1)[:, None]
            var = (svis * ((c - mean) ** 2).sum(-1)).sum(0) / k.clamp(min=1)
            data = (use * var).sum() / use.sum().clamp(min=1) * 1e3
            smooth = ((o[edges[:, 0]] - o[edges[:, 1]]) ** 2).mean() * 1e4
            sil = (_sample(dt, px[:, :len(X0)])[..., 0] ** 2).mean(1).sum()
            loss = data + settings.stereo_smooth * smooth + settings.silhouette * sil
            loss.backward()
            return loss

        opt.step(closure)
    o = (reach * torch.tanh(offset / reach)).detach()
    return GarmentMesh(vertices=(X0 + o[:, None] * n).cpu().numpy().astype(np.float64), faces=mesh.faces,
                       frame=mesh.frame, segments=mesh.segments)


# ---- 3. node motions --------------------------------------------------------------------------------------------
def node_motions(tracks: GarmentTracks, ref: int, nodes: np.ndarray, centers: np.ndarray, patch: int = 40,
                 reach: float = 0.15, min_vertices: int = 6) -> NodeMotions:
    """Step 3 of the module docstring: `centers` [M, 3] the nodes `nodes` [M] at the reference frame index `ref`.
    A node's patch is its `patch` nearest surface vertices within `reach` metres (a hull node may sit inside the
    garment's volume, centimetres from its surface); nodes with fewer than `min_vertices` there are left out."""
    from scipy.spatial import cKDTree

    X = tracks.vertices  # [F, V, 3]
    tree = cKDTree(X[ref])
    rows, Rs, ts, counts, seens = [], [], [], [], []
    for k, c in enumerate(centers):
        dist, idx = tree.query(c, k=min(patch, len(X[ref])), distance_upper_bound=reach)
        idx = np.atleast_1d(idx)[np.isfinite(np.atleast_1d(dist))]
        if len(idx) < min_vertices:
            continue
        Y = X[:, idx]  # [F, p, 3]
        R, t = rigid_align(np.broadcast_to(Y[ref], Y.shape), Y)  # [F, 3, 3], [F, 3]: y = R x + t
        rows.append(int(nodes[k]))
        Rs.append(R)
        ts.append(t)
        counts.append(len(idx))
        seens.append((tracks.seen[:, idx] >= 2).mean(1))
    F = X.shape[0]
    if not rows:
        return NodeMotions(np.zeros(0, dtype=np.int64), np.zeros((F, 0, 3, 3)), np.zeros((F, 0, 3)),
                           np.zeros(0, dtype=np.int64), np.zeros((F, 0)))
    return NodeMotions(nodes=np.asarray(rows), rotation=np.stack(Rs, 1), translation=np.stack(ts, 1),
                       vertices=np.asarray(counts), seen=np.stack(seens, 1))


def placement(rotation: np.ndarray, center: np.ndarray, skeleton_rotation: np.ndarray, skeleton_center: np.ndarray,
              tracked: np.ndarray, ref: int) -> tuple[np.ndarray, np.ndarray]:
    """The tracked nodes' placement on every training frame: `rotation` [F, M, 3, 3] and `center` [F, M, 3] where
    `tracked` [F] (the tracker's frames; `ref` the reference frame index); on a frame the tracker did not reach, the
    skeleton's placement (`skeleton_rotation`, `skeleton_center`, Eq. 1-2) with the garment's offset from it at the
    last frame tracked on the way there from the reference, held in the node's skeleton frame (A^-1 R, A^-1 (c - c_s)):
    the placement does not jump where the tracker stops. -> (rotation, center) [F, M, 3, 3], [F, M, 3]."""
    held = np.arange(len(tracked))  # each frame's source: itself where tracked, else the last tracked frame before it
    for f in list(range(ref + 1, len(held))) + list(range(ref - 1, -1, -1)):
        if not tracked[f]:
            held[f] = held[f - 1] if f > ref else held[f + 1]
    A, c = skeleton_rotation, skeleton_center
    offset_r = np.linalg.solve(A[held], rotation[held])  # [F, M, 3, 3]
    offset_t = np.linalg.solve(A[held], (center[held] - c[held])[..., None])[..., 0]  # [F, M, 3]
    return A @ offset_r, c + np.einsum("fmij,fmj->fmi", A, offset_t)


def capture_input(capture, body, template, frames: list[int], views: list[str]) -> TrackingInput:
    """The `TrackingInput` of a `ProjectCapture`'s training `frames` x `views`, the body posed by its fits."""
    from avatarctl.body.lbs import blend_transforms

    posed = body.pose(capture.motion.for_frames(frames))
    joints = posed.joint_transforms.double()  # [F, J, 4, 4]
    weights = template.skin_weights.double()

    def transforms(fi: int, vertex: np.ndarray) -> np.ndarray:
        return blend_transforms(weights[torch.as_tensor(vertex)], joints[fi:fi + 1])[0].numpy()

    # the body's up axis: the rest pose's longest extent, towards the side holding most of the body (the head and
    # arms above the hips), turned by the blended transform of the vertex nearest the rest body's centroid
    rest = template.vertices.detach().double().numpy()
    axis = int(np.argmax(rest.max(0) - rest.min(0)))
    up_rest = np.eye(3)[axis] * (1.0 if rest[:, axis].mean() >= 0.5 * (rest[:, axis].max() + rest[:, axis].min())
                                 else -1.0)
    centre = np.array([int(np.argmin(np.linalg.norm(rest - rest.mean(0), axis=1)))])
    up = np.stack([transforms(fi, centre)[0, :3, :3] @ up_rest for fi in range(len(frames))])

    return TrackingInput(frames=tuple(int(f) for f in frames), cameras=tuple(capture.cameras[v] for v in views),
                         image=lambda c, f: capture.image(views[c], f),
                         mask=lambda c, f: capture.mask(views[c], f) > 0,
                         body_vertices=posed.vertices.detach().double().numpy(),
                         body_faces=template.faces.numpy(), body_transforms=transforms, up=up)
