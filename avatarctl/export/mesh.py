"""A fitted radiance field -> a coloured triangle mesh: density grid, marching cubes, baked vertex colours.

Steps (`extract_mesh`):
1. a regular grid of spacing `voxel` (metres) over the box of the node supports (posed node centres n_i grown by
   the Eq. 6 support radius sigma sqrt(-2 ln eps)); only grid points within the support radius of a node are
   queried (elsewhere Eq. 6 makes every blending weight zero, so the density is exactly 0), and only near the
   surface: a grid twice as coarse is sampled first, and the fine grid is queried only where its cells come near
   the level (`density_grid`);
2. marching cubes (scikit-image, Lewiner) of the density sigma (1/metre) at the level `threshold`; a ray crossing
   a slab of density `threshold` and thickness d keeps exp(-threshold * d) of its light: the default
   `DEFAULT_THRESHOLD` = 10 / metre puts the surface where 10 cm of such matter would be 63 % opaque. Lower than
   the "hard surface" levels of NeRF meshing because a fitted SLRF's cloth (a skirt) is soft: on synth small
   (10 min cpu fit, 8 mm grid, frame 0, 4 held-out views) levels 5 / 10 / 20 / 40 gave mesh PSNR
   21.01 / 21.26 / 18.13 / 16.28 dB (holes open in the skirt above 10; the volume render: 22.38 dB);
   The body level (`body_level`) is a level from the field's own densities: the density just inside the body
   model's skin (1 cm in along the template's normals, the body posed like the frame) is what the surface must
   enclose; the level is its `BODY_QUANTILE` quantile, at most `DEFAULT_THRESHOLD`. A well-fitted field (skin
   densities in the hundreds) gets 10; a soft one (a short fit: the demo's tiny project, 533 steps, has a median
   skin density of 3.3 / m) a lower level, so thin parts (neck, thighs under a skirt) stay inside the surface
   instead of falling apart. The export's default level is the body level times a factor chosen by scoring
   candidate meshes against training images (`export.level`);
3. connected components with fewer than `min_component` of the faces (floaters of stray density) are dropped;
4. vertex colours (`bake_colours`): each vertex is looked at head-on, with a ray from just outside the surface
   (v + 2 voxels * n, n the outward normal) along -n, volume-rendered through the field (`slrf_ray_colour`, the
   compositing of an image) over `BAKE_LENGTH` = 30 cm, the body's thickness, with `BAKE_SAMPLES` = 32 samples,
   over the fit's background: the colour is what the volume render shows where a camera looks at that surface
   head-on. A soft field (a short fit) is partly transparent and its images are darker than its colour head's
   output; the opaque mesh must show the composite, not the colour divided by the opacity: on the demo's tiny
   project (frame 0, 2 held-out views) the divided 4 cm bake showed the olive top 35-53 levels too bright (mesh
   17.31 dB vs volume 22.03 dB), the composite is within 5 levels (20.51 dB). For an opaque field the two agree.
   One view direction per vertex: the view dependence of the colour head (Eq. 7) is frozen into the colour seen
   along the normal. Without a background (`background=None`) the colour is the composite divided by its opacity
   (the colour of what is hit). A Gaussian-field avatar's mesh is coloured from its rasterized images instead
   (`export.view_colours`; `stages.export` picks the colouring by the field: `VertexColourFn`).

The field is passed as callables (`DensityFn`, `RayColourFn`) so the extraction is tested on an analytic sphere;
`slrf_density` / `slrf_ray_colour` adapt a fitted `SlrfAvatar` and one frame of its `NodeState`.

Conventions: metres, world frame of the field (posed space for a frame, canonical space for the rest pose);
faces wound counter-clockwise seen from outside (outward normals).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable

import numpy as np

if TYPE_CHECKING:
    from avatarctl.model.avatar import NodeState, SlrfAvatar

DEFAULT_THRESHOLD = 10.0  # 1/metre, see the module docstring
BODY_QUANTILE = 0.25  # `body_level`: the share of the skin probes allowed below the level
BODY_DEPTH = 0.01  # metres: `body_level` probes this far inside the skin
BAKE_LENGTH = 0.3  # metres of the head-on colour ray (module docstring, step 4)
BAKE_SAMPLES = 32
DEFAULT_VOXEL = 0.008  # metres
BAKE_RULE = (f"volume render of a {BAKE_LENGTH * 100:g} cm ray ({BAKE_SAMPLES} samples) looking at each vertex along "
             "-normal from 2 voxels outside, composited over the fit's background (one view direction per vertex)")
DensityFn = Callable[[np.ndarray], np.ndarray]  # points [points, 3] -> sigma [points] (1/metre)
RayColourFn = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]  # (origins, dirs) [rays, 3] ->
#                                                                          (rgb [rays, 3] over black, alpha [rays])
VertexColourFn = Callable[[np.ndarray, np.ndarray, np.ndarray, "np.ndarray | None"], tuple[np.ndarray, np.ndarray]]
# (vertices [V, 3], faces [F, 3], normals [V, 3], which [V] bool or None = all) -> (colours [V, 3] in [0, 1], done
# [V] bool: the vertices coloured, at least `which`; `head_on_bake` computes only those, `export.view_colours` all)


@dataclass(frozen=True)
class ColouredMesh:
    """A triangle mesh with per-vertex colours."""

    vertices: np.ndarray  # [verts, 3] float32, metres
    faces: np.ndarray  # [faces, 3] int32, counter-clockwise seen from outside
    normals: np.ndarray  # [verts, 3] float32 unit outward normals
    colours: np.ndarray  # [verts, 3] float32 in [0, 1], display (sRGB-encoded) values as the volume render gives

    def __post_init__(self) -> None:
        V = self.vertices.shape[0]
        assert self.vertices.shape == (V, 3), f"vertices: expected [verts, 3], got {self.vertices.shape}"
        assert self.faces.ndim == 2 and self.faces.shape[1] == 3, f"faces: expected [faces, 3], got {self.faces.shape}"
        assert self.normals.shape == (V, 3), f"normals: expected [{V}, 3], got {self.normals.shape}"
        assert self.colours.shape == (V, 3), f"colours: expected [{V}, 3], got {self.colours.shape}"

    @property
    def num_vertices(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def num_faces(self) -> int:
        return int(self.faces.shape[0])


@dataclass(frozen=True)
class DensityGrid:
    """Densities on a regular grid: point (i, j, k) is origin + voxel * (i, j, k)."""

    sigma: np.ndarray  # [nx, ny, nz] float32, 1/metre (0 outside the node supports)
    origin: np.ndarray  # [3] metres, the first grid point
    voxel: float  # metres
    queried: int  # grid points the field was evaluated at (inside a node support)


class NoSurfaceError(ValueError):
    """The density never crosses the threshold (nothing to mesh)."""


class GridTooLargeError(ValueError):
    """The grid over the node supports would hold more points than allowed at this voxel size."""


def body_level(density: DensityFn, body_vertices: np.ndarray, body_faces: np.ndarray,
               quantile: float = BODY_QUANTILE, depth: float = BODY_DEPTH,
               ceiling: float = DEFAULT_THRESHOLD) -> float:
    """The surface level (1/metre) from the field's own densities (module docstring, step 2): the `quantile` of sigma
    at the body model's vertices moved `depth` metres inside along their normals, at most `ceiling`.

    body_vertices [V, 3] in the field's frame (the body posed like the field), body_faces [faces, 3]
    counter-clockwise from outside. Raises `NoSurfaceError` when the field is empty at the body."""
    from avatarctl.geometry.normals import vertex_normals

    v = np.asarray(body_vertices, np.float64)
    probes = v - depth * vertex_normals(v, np.asarray(body_faces))
    sigma = np.asarray(density(probes.astype(np.float32)), np.float64)
    level = float(np.quantile(sigma, quantile))
    if not level > 0:
        raise NoSurfaceError(f"the density inside the body is 0 at {100 * quantile:g} % of it (max "
                             f"{sigma.max():.3g}/m)")
    return min(level, ceiling)


def support_box(centers: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """[nodes, 3] node centres, support radius (metres) -> (lo [3], hi [3]) of the union of the support spheres."""
    c = np.asarray(centers, dtype=np.float64)
    return c.min(axis=0) - radius, c.max(axis=0) + radius


def density_grid(density: DensityFn, centers: np.ndarray, radius: float, voxel: float, level: float | None = None,
                 coarse: int = 2, chunk: int = 65536, max_points: int = 60_000_000) -> DensityGrid:
    """Sample `density` on the grid of spacing `voxel` over the node supports (module docstring, step 1).

    centers [nodes, 3] metres; radius: the support radius; the grid is padded by one voxel of zeros on every side
    so that marching cubes closes the surface. With a `level` (the iso-level to be extracted) the grid is refined
    from a `coarse`-times coarser one: the field is queried on the coarse lattice, interpolated (trilinear) to the
    fine one, and queried again only in the coarse cells whose corners come near the level (some corner >= level/4
    and some <= 4 level, grown by one cell); cells far inside or far outside keep the interpolated values, on the
    right side of the level. Detail thinner than a coarse cell can be missed; `coarse=1` queries every point.
    """
    from scipy.spatial import cKDTree

    if not voxel > 0:
        raise ValueError(f"voxel must be > 0 metres, got {voxel}")
    lo, hi = support_box(centers, radius)
    lo = lo - voxel
    k = int(coarse) if level is not None and coarse > 1 else 1
    shape = tuple(k * int(np.ceil(n / k)) + 1 for n in np.ceil((hi + voxel - lo) / voxel).astype(int))
    total = int(np.prod(shape))
    if total > max_points:
        raise GridTooLargeError(f"a {shape[0]}x{shape[1]}x{shape[2]} grid ({total:,} points) is too large at voxel "
                         f"{voxel} m; use a larger voxel")
    tree = cKDTree(np.asarray(centers, dtype=np.float64))
    if k == 1:
        sigma, queried = _sample_lattice(density, tree, radius, lo, voxel, shape, None, chunk)
        return DensityGrid(sigma=sigma, origin=lo.astype(np.float64), voxel=float(voxel), queried=queried)
    from scipy.ndimage import binary_dilation, zoom

    cshape = tuple((n - 1) // k + 1 for n in shape)
    csigma, queried = _sample_lattice(density, tree, radius, lo, voxel * k, cshape, None, chunk)
    corners = [csigma[a:a + cshape[0] - 1, b:b + cshape[1] - 1, c:c + cshape[2] - 1]
               for a in (0, 1) for b in (0, 1) for c in (0, 1)]
    cmax, cmin = np.max(corners, axis=0), np.min(corners, axis=0)  # [cells]
    near = binary_dilation((cmax >= level / 4.0) & (cmin <= level * 4.0), iterations=1)
    refine = np.zeros(shape, bool)
    refine[:-1, :-1, :-1] = near.repeat(k, 0).repeat(k, 1).repeat(k, 2)
    refine[-1], refine[:, -1], refine[:, :, -1] = refine[-2], refine[:, -2], refine[:, :, -2]
    sigma = zoom(csigma, [n / c for n, c in zip(shape, cshape)], order=1, grid_mode=False).astype(np.float32)
    assert sigma.shape == shape, f"zoom gave {sigma.shape}, expected {shape}"
    fine, fine_queried = _sample_lattice(density, tree, radius, lo, voxel, shape, refine, chunk)
    sigma[refine] = fine[refine]
    return DensityGrid(sigma=sigma, origin=lo.astype(np.float64), voxel=float(voxel), queried=queried + fine_queried)


def _sample_lattice(density: DensityFn, tree, radius: float, lo: np.ndarray, step: float, shape: tuple[int, ...],
                    select: np.ndarray | None, chunk: int) -> tuple[np.ndarray, int]:
    """sigma [shape] on the lattice lo + step * (i, j, k): the field at the points within `radius` of a node (and in
    `select` [shape] bool when given), 0 elsewhere; -> (sigma, points queried). One x-slab at a time."""
    sigma = np.zeros(int(np.prod(shape)), dtype=np.float32)
    axes = [lo[d] + step * np.arange(shape[d]) for d in range(3)]
    plane = shape[1] * shape[2]
    gy, gz = np.meshgrid(axes[1], axes[2], indexing="ij")  # [ny, nz]
    yz = np.stack([gy.ravel(), gz.ravel()], axis=-1)  # [ny * nz, 2]
    pending_idx: list[np.ndarray] = []
    pending_pts: list[np.ndarray] = []
    pending = queried = 0

    def flush() -> None:
        nonlocal pending
        if pending:
            idx, pts = np.concatenate(pending_idx), np.concatenate(pending_pts)
            sigma[idx] = np.asarray(density(pts.astype(np.float32)), dtype=np.float32)
        pending_idx.clear()
        pending_pts.clear()
        pending = 0

    for i, x in enumerate(axes[0]):
        cand = np.arange(plane) if select is None else np.flatnonzero(select[i].ravel())
        if cand.size == 0:
            continue
        pts = np.concatenate([np.full((cand.size, 1), x), yz[cand]], axis=-1)  # [candidates, 3]
        d, _ = tree.query(pts, k=1, distance_upper_bound=radius)
        inside = np.flatnonzero(np.isfinite(d))
        if inside.size:
            pending_idx.append(i * plane + cand[inside])
            pending_pts.append(pts[inside])
            pending += inside.size
            queried += inside.size
        if pending >= chunk:
            flush()
    flush()
    return sigma.reshape(shape), queried


def marching_cubes(grid: DensityGrid, threshold: float, min_component: float = 0.01
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Iso-surface of `grid` at `threshold` (1/metre) -> vertices [verts, 3] (metres), faces [faces, 3] (outward,
    counter-clockwise), normals [verts, 3] (outward unit). Components with fewer than `min_component` of all faces
    are dropped (0 keeps all). Raises `NoSurfaceError` when the density never reaches the threshold."""
    from skimage.measure import marching_cubes as skimage_mc

    peak = float(grid.sigma.max()) if grid.sigma.size else 0.0
    if not peak > threshold:
        raise NoSurfaceError(f"the density never reaches the threshold {threshold:g}/m (max {peak:.3g}/m)")
    verts, faces, normals, _ = skimage_mc(grid.sigma, level=threshold, spacing=(grid.voxel,) * 3,
                                          method="lewiner", allow_degenerate=False)
    verts = verts + grid.origin[None]  # skimage's normals (descent) point out of the matter already,
    faces = faces[:, ::-1]  # but its triangles are clockwise seen from outside: reverse them
    verts, faces, normals = _drop_small_components(verts, faces, normals, min_component)
    n = np.linalg.norm(normals, axis=-1, keepdims=True)
    return verts.astype(np.float32), faces.astype(np.int32), (normals / np.maximum(n, 1e-12)).astype(np.float32)


def _face_components(faces: np.ndarray, num_vertices: int) -> np.ndarray:
    """[faces] the face-connected component of each face (labels 0 ..)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    rows = np.concatenate([faces[:, 0], faces[:, 1], faces[:, 2]])
    cols = np.concatenate([faces[:, 1], faces[:, 2], faces[:, 0]])
    _, label = connected_components(coo_matrix((np.ones(rows.size), (rows, cols)),
                                               shape=(num_vertices, num_vertices)), directed=False)
    return label[faces[:, 0]]


def mesh_pieces(faces: np.ndarray, num_vertices: int) -> tuple[int, float]:
    """faces [faces, 3] of a mesh of `num_vertices` -> (connected pieces, the largest piece's share of the faces)."""
    if faces.shape[0] == 0:
        return 0, 0.0
    _, counts = np.unique(_face_components(np.asarray(faces), num_vertices), return_counts=True)
    return int(counts.size), float(counts.max() / faces.shape[0])


def _drop_small_components(verts: np.ndarray, faces: np.ndarray, normals: np.ndarray, min_fraction: float
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Keep the face-connected components with at least `min_fraction` of the faces; reindex the vertices."""
    if min_fraction <= 0 or faces.shape[0] == 0:
        return verts, faces, normals
    V = verts.shape[0]
    face_label = _face_components(faces, V)
    counts = np.bincount(face_label)
    keep_faces = counts[face_label] >= min_fraction * faces.shape[0]
    faces = faces[keep_faces]
    used = np.zeros(V, bool)
    used[faces.ravel()] = True
    remap = np.cumsum(used) - 1
    return verts[used], remap[faces], normals[used]


def bake_colours(ray_colour: RayColourFn, vertices: np.ndarray, normals: np.ndarray, offset: float,
                 background: tuple[float, float, float] | None = None, chunk: int = 16384) -> np.ndarray:
    """Vertex colours [verts, 3] in [0, 1] seen head-on (module docstring, step 4): rays from v + offset * n along
    -n; colour = composited rgb over `background` (rgb + (1 - alpha) background), or without one rgb / alpha
    (black where nothing is hit)."""
    out = np.zeros((vertices.shape[0], 3), np.float32)
    bg = None if background is None else np.asarray(background, np.float32)
    for s in range(0, vertices.shape[0], chunk):
        v, n = vertices[s:s + chunk].astype(np.float32), normals[s:s + chunk].astype(np.float32)
        rgb, alpha = ray_colour(v + offset * n, -n)
        shown = rgb / np.maximum(alpha, 1e-6)[:, None] if bg is None else rgb + (1.0 - alpha)[:, None] * bg
        out[s:s + chunk] = np.clip(shown, 0.0, 1.0)
    return out


def head_on_bake(ray_colour: RayColourFn, offset: float, background: tuple[float, float, float] | None = None
                 ) -> VertexColourFn:
    """Step 4 as a `VertexColourFn`: `bake_colours` of the vertices asked for (the rest stay black)."""

    def colour(vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray, which: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
        if which is None:
            return (bake_colours(ray_colour, vertices, normals, offset, background),
                    np.ones(vertices.shape[0], bool))
        out = np.zeros((vertices.shape[0], 3), np.float32)
        out[which] = bake_colours(ray_colour, vertices[which], normals[which], offset, background)
        return out, np.asarray(which, bool)

    return colour


def extract_mesh(density: DensityFn, colour: VertexColourFn, centers: np.ndarray, radius: float, voxel: float,
                 threshold: float = DEFAULT_THRESHOLD, min_component: float = 0.01) -> tuple[ColouredMesh, int]:
    """Steps 1-4 of the module docstring -> (the coloured mesh, grid points queried). `colour`: step 4's
    `head_on_bake(ray_colour, 2 * voxel, background)`, or another colouring (`export.view_colours`)."""
    grid = density_grid(density, centers, radius, voxel, level=threshold)
    verts, faces, normals = marching_cubes(grid, threshold, min_component)
    colours, _ = colour(verts, faces, normals, None)
    return ColouredMesh(vertices=verts, faces=faces, normals=normals, colours=colours), grid.queried


# ---- adapters for a fitted SlrfAvatar ----------------------------------------------------------------------------
def slrf_density(model: "SlrfAvatar", state: "NodeState", slot: int = 0) -> DensityFn:
    """sigma(p) of frame `slot` of `state`: the density head at world points (1/metre, 0 outside the supports)."""
    import torch

    dev = state.centers.device

    def density(points: np.ndarray) -> np.ndarray:
        p = torch.from_numpy(np.ascontiguousarray(points, dtype=np.float32)).to(dev)
        dirs = torch.zeros_like(p)
        dirs[:, 2] = 1.0  # the density head does not depend on the view direction
        frame = torch.full((p.shape[0],), slot, dtype=torch.long, device=dev)
        with torch.no_grad():
            _, sigma, _ = model.query(p, dirs, frame, state)
        return sigma.float().cpu().numpy()

    return density


def slrf_ray_colour(model: "SlrfAvatar", state: "NodeState", slot: int = 0, length: float = BAKE_LENGTH,
                    samples: int = BAKE_SAMPLES) -> RayColourFn:
    """Volume-render the first `length` metres of rays of frame `slot` over black with `samples` samples (the same
    compositing as an image, `render.volume.march`): (origins, dirs) [rays, 3] -> (rgb [rays, 3], alpha [rays])."""
    import torch

    from avatarctl.render.volume import march

    dev = state.centers.device
    black = torch.zeros(3, device=dev)

    def field(points: torch.Tensor, dirs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        rays, n = points.shape[:2]  # [rays, samples, 3]
        frame = torch.full((rays * n,), slot, dtype=torch.long, device=dev)
        rgb, sigma, _ = model.query(points.reshape(-1, 3), dirs.reshape(-1, 3), frame, state)
        return rgb.reshape(rays, n, 3), sigma.reshape(rays, n)

    def ray_colour(origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        o = torch.from_numpy(np.ascontiguousarray(origins, dtype=np.float32)).to(dev)
        d = torch.nn.functional.normalize(torch.from_numpy(np.ascontiguousarray(dirs, dtype=np.float32)), dim=-1)
        near = o.new_zeros(o.shape[0])
        with torch.no_grad():
            out = march(field, o, d.to(dev), near, near + length, samples, black, False, None)
        return out.rgb.float().cpu().numpy(), out.alpha.float().cpu().numpy()

    return ray_colour


def rest_node_state(model: "SlrfAvatar") -> "NodeState":
    """The nodes in the canonical (rest) pose: every joint transform M_j = identity (canonical -> canonical), pose
    features 0, latent z = 0 (a novel pose: no time stamp, no cVAE encoder), so the field lives in the template's
    canonical space."""
    import torch

    from avatarctl.model.avatar import FrameConditioning

    J, dev = model.num_joints, model.node_rest.device
    cond = FrameConditioning(joint_transforms=torch.eye(4, device=dev).expand(1, J, 4, 4).clone(),
                             pose_features=torch.zeros(1, J, 3, device=dev), time=torch.zeros(1, device=dev),
                             frame_ids=torch.full((1,), -1, dtype=torch.long, device=dev))
    with torch.no_grad():
        return model.node_state(cond, mode="zero")
