"""Hull nodes: put some of the N nodes where the masks show the subject beyond the body (a deviation from the paper,
issue 18; `ModelConfig.hull`, a `HullConfig`).

The paper places all N nodes on the body surface (farthest point sampling, Sec. 3.1). A loose skirt reaches beyond
every node's support (sigma sqrt(-2 ln eps) = 0.186 m) in a twirl: those rays return background and nothing pulls
a node out there. With `hull.nodes = K > 0`, N - K nodes are sampled on the surface as before and K are placed from
the training masks:

1. for up to `max_frames` training frames, a voxel grid around the posed body (expanded by `margin`) is carved by
   the training views' masks (a voxel is kept when it projects inside the mask of every view that sees it, and at
   least two views see it): the visual hull of that frame. Of the hull, only voxels that at least one view puts on
   a mask pixel the posed body's own silhouette (grown by `explain_px`) does not cover are kept: a few views cannot
   carve the concavities around a body (4 views leave 35 litres of phantom volume beside the arms and torso of the
   tight-clothing capture, none of it garment), but every phantom voxel projects onto the body in every view, while
   a skirt shows where the body is not;
2. hull voxels farther than `min_dist` from every posed surface node are "off-body";
3. each is mapped to the canonical space with the inverse skinning transform of its nearest posed body vertex
   (Eq. 1 inverted); of the pooled points, only the 5 cm cells that points of at least 15 % of the carved frames (and
   at least two; one carved frame keeps all its cells) fall in are kept (one frame's phantom hull volume, or a hem
   mapped through a swinging leg, is not); of these, only the connected groups of cells (cubes sharing a face, an
   edge or a corner) that come within `min_dist` of the canonical body are kept (`worn_cells`): a garment hangs from
   the body, while a mask error that persists (a patch of floor or shadow MediaPipe keeps in its masks) lies apart
   from it;
4. K nodes are chosen among them by farthest point sampling, starting from the surface nodes (so they go where the
   surface nodes are not), each skinned like its nearest canonical body vertex. When fewer than K points remain
   (tight clothing; one training view, which carves nothing), the missing nodes go on the surface, farthest from
   the others: the placement is then the paper's.

The node then moves like that vertex (Eq. 3) plus its learned Delta n, like any other node.

`hull.nodes = "auto"` decides from the same survey (`decide`): K = `hull.auto_fraction` N hull nodes when the
persistent off-body cells hold at least `hull.auto_min_volume` of the body's volume (the template mesh's), else
none (the paper's placement, bit for bit). Measured (docs/experiments/hull_auto_2026-11-25): synth small (skirt,
8 views) 281 %, synth tiny (skirt, 4 views) 461 %, synth tight (4 views) and monocular (1 view) 0 %.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from avatarctl.geometry.hull import carve
from avatarctl.model.deformer import farthest_point_sampling


@dataclass(frozen=True)
class HullSurvey:
    """What the training masks show beyond the body (steps 1-3 of the module docstring), in canonical space."""

    cells: np.ndarray  # [C, 3] canonical points of the persistent off-body cells, metres
    cell: float  # side of a cell, metres
    frames: int  # training frames carved
    body_volume: float  # the canonical template mesh's volume, m^3
    apart: int = 0  # persistent cells dropped as apart from the body (`worn_cells`)

    def __post_init__(self) -> None:
        assert self.cells.ndim == 2 and self.cells.shape[1] == 3, f"cells {self.cells.shape}"

    @property
    def volume(self) -> float:
        """Volume of the persistent off-body cells, m^3."""
        return len(self.cells) * self.cell ** 3

    @property
    def share(self) -> float:
        """`volume` as a share of the body's volume (the figure `hull.nodes = "auto"` decides on)."""
        return self.volume / self.body_volume if self.body_volume > 0 else 0.0

    def describe(self) -> str:
        return (f"{len(self.cells):,} persistent off-body cells of {self.frames} frames ({self.volume * 1e3:.1f} l, "
                f"{100 * self.share:.1f} % of the body volume{self._apart()})")

    def _apart(self) -> str:
        return f"; {self.apart:,} more apart from the body, dropped" if self.apart else ""


@dataclass(frozen=True)
class HullNodes:
    """K nodes placed off the body (see the module docstring)."""

    rest: torch.Tensor  # [K, 3] canonical positions, metres, float32
    vertex: torch.Tensor  # [K] long: nearest canonical template vertex (its skinning weights are the node's)
    candidates: int  # pooled off-body hull points they were chosen from
    frames: int  # training frames carved
    off_body: int  # nodes placed off the body (< K when the hull showed fewer points: the others on the surface)
    survey: HullSurvey  # what they were chosen from

    def __post_init__(self) -> None:
        assert self.rest.ndim == 2 and self.rest.shape[1] == 3, f"rest {tuple(self.rest.shape)}"
        assert self.vertex.shape == (self.rest.shape[0],), f"vertex {tuple(self.vertex.shape)}"


def off_body_canonical(points: np.ndarray, posed_vertices: torch.Tensor, vertex_transforms: torch.Tensor,
                       posed_nodes: np.ndarray, min_dist: float) -> np.ndarray:
    """Hull `points` [M, 3] of one frame farther than `min_dist` from every posed surface node [N, 3] -> their
    canonical positions [M', 3]: the inverse of the blended transform [V, 4, 4] of the nearest posed vertex [V, 3]."""
    from scipy.spatial import cKDTree

    if not len(points):
        return np.zeros((0, 3))
    d, _ = cKDTree(posed_nodes).query(points)
    far = points[d > min_dist]
    if not len(far):
        return np.zeros((0, 3))
    _, vi = cKDTree(posed_vertices.detach().cpu().numpy()).query(far)
    T = torch.linalg.inv(vertex_transforms[torch.as_tensor(vi)].double())  # [M', 4, 4]
    x = torch.as_tensor(far, dtype=torch.float64)
    return ((T[:, :3, :3] @ x[..., None])[..., 0] + T[:, :3, 3]).numpy()


def persistent_cells(per_frame: list[np.ndarray], cell: float, min_frames: int) -> np.ndarray:
    """Canonical points of several frames (a list of [M_t, 3]) -> [C, 3] the mean point of each cube of side `cell`
    that points of at least `min_frames` frames fall in. Drops what one frame's carving or skinning got wrong
    (phantom hull volumes, a hem mapped through a swinging leg) and keeps where the garment keeps coming back."""
    if not per_frame or not sum(len(p) for p in per_frame):
        return np.zeros((0, 3))
    pts = np.concatenate(per_frame)
    frame = np.concatenate([np.full(len(p), t) for t, p in enumerate(per_frame)])
    keys = np.floor(pts / cell).astype(np.int64)
    _, inv = np.unique(keys, axis=0, return_inverse=True)
    inv = inv.ravel()
    n = inv.max() + 1
    frames_in = np.zeros(n, dtype=np.int64)
    pair = np.unique(np.stack([inv, frame]), axis=1)  # distinct (cell, frame)
    np.add.at(frames_in, pair[0], 1)
    sums = np.zeros((n, 3))
    np.add.at(sums, inv, pts)
    mean = sums / np.bincount(inv, minlength=n)[:, None]
    return mean[frames_in >= min_frames]


def worn_cells(cells: np.ndarray, cell: float, body_vertices: np.ndarray, reach: float) -> tuple[np.ndarray, int]:
    """The cells of `persistent_cells` ([C, 3], cubes of side `cell`) that belong to a connected group (cubes
    sharing a face, an edge or a corner) of which at least one cell lies within `reach` of the canonical body
    (`body_vertices` [V, 3]) -> (those cells [C', 3], how many were dropped)."""
    from scipy import ndimage
    from scipy.spatial import cKDTree

    if not len(cells):
        return cells, 0
    keys = np.floor(cells / cell).astype(np.int64)
    keys -= keys.min(0)
    grid = np.zeros(keys.max(0) + 1, dtype=bool)
    grid[tuple(keys.T)] = True
    labels, _ = ndimage.label(grid, structure=np.ones((3, 3, 3), dtype=bool))
    group = labels[tuple(keys.T)]  # [C] 1..n
    near = cKDTree(body_vertices).query(cells)[0] <= reach
    keep = np.isin(group, np.unique(group[near]))
    return cells[keep], int((~keep).sum())


def persistence_threshold(frames: int, min_share: float) -> int:
    """How many of `frames` carved frames must show a cell for `persistent_cells` to keep it: `min_share` of them and
    at least two, but never more than there are (one carved frame, a static multi-view capture, keeps its cells)."""
    return min(frames, max(2, int(np.ceil(min_share * frames))))


def mesh_volume(vertices: torch.Tensor, faces: torch.Tensor) -> float:
    """|signed volume| (m^3) of the closed triangle mesh `vertices` [V, 3] / `faces` [F, 3] (divergence theorem)."""
    v = vertices.detach().double()
    a, b, c = v[faces[:, 0]], v[faces[:, 1]], v[faces[:, 2]]
    return abs(float((a * torch.linalg.cross(b, c)).sum()) / 6.0)


def survey_hull(capture, body, template, frames: list[int], views: list[str], surface_vertex: torch.Tensor,
                min_dist: float, *, voxel: float = 0.025, margin: float = 0.35, max_frames: int = 24,
                min_share: float = 0.15, explain_px: int | None = 2) -> HullSurvey:
    """Steps 1-3 of the module docstring for `capture` (a `ProjectCapture`), its masks of `frames` x `views`:
    the persistent off-body cells, in canonical space. `surface_vertex` [M] long: the template vertices the surface
    nodes sit on.
    `explain_px`: the posed body's silhouette is grown by this many pixels before it explains a mask pixel
    (body-fit error, anti-aliased mask edges); None: no pixel is explained (the carve before 2026-11-25)."""
    import cv2

    from avatarctl.body.lbs import blend_transforms
    from avatarctl.geometry.silhouette import rasterize_silhouette

    use = [frames[i] for i in np.unique(np.linspace(0, len(frames) - 1, min(max_frames, len(frames))).astype(int))]
    motion = capture.motion.for_frames(use)
    posed = body.pose(motion)
    W = template.skin_weights.double()
    faces = template.faces.numpy()
    cams = [capture.cameras[v] for v in views]
    grow = np.ones((2 * (explain_px or 0) + 1,) * 2, dtype=np.uint8)
    pooled = []
    for t, frame in enumerate(use):
        V = posed.vertices[t].double()
        lo = V.amin(0).numpy() - margin
        hi = V.amax(0).numpy() + margin
        sil = None if explain_px is None else [
            cv2.dilate(rasterize_silhouette(c, V.numpy(), faces, supersample=1).astype(np.uint8), grow) > 0
            for c in cams]
        pts = carve(cams, [capture.mask(v, frame) for v in views], lo, hi, voxel, explained=sil)
        Tv = blend_transforms(W, posed.joint_transforms[t:t + 1].double())[0]  # [V, 4, 4]
        pooled.append(off_body_canonical(pts, V, Tv, V[surface_vertex].numpy(), min_dist))
    cells = persistent_cells(pooled, cell=2 * voxel, min_frames=persistence_threshold(len(use), min_share))
    cells, apart = worn_cells(cells, 2 * voxel, template.vertices.detach().cpu().numpy(), min_dist)
    return HullSurvey(cells=cells, cell=2 * voxel, frames=len(use),
                      body_volume=mesh_volume(template.vertices, template.faces), apart=apart)


def auto_hull_nodes(survey: HullSurvey, k: int, min_volume: float) -> int:
    """`hull.nodes = "auto"`: `k` (`ModelConfig.hull_auto_nodes`) when the persistent off-body cells hold at least
    `min_volume` of the body's volume, else 0 (the paper's placement)."""
    return k if survey.share >= min_volume and len(survey.cells) else 0


def choose_hull_nodes(survey: HullSurvey, template, surface_rest: torch.Tensor, k: int) -> HullNodes:
    """Step 4 of the module docstring: K nodes among `survey.cells` by farthest point sampling from the surface
    nodes `surface_rest` [N - K, 3]; too few cells: the rest on the surface, farthest from the others."""
    from scipy.spatial import cKDTree

    cand = survey.cells
    tpl = template.vertices.detach().double()
    off = min(k, len(cand))
    rest = torch.zeros(0, 3, dtype=torch.float64)
    if off:
        cand_t = torch.as_tensor(cand, dtype=torch.float64)
        rest = cand_t[farthest_point_sampling(cand_t, off, existing=surface_rest)]
    _, vi = cKDTree(tpl.numpy()).query(rest.numpy()) if off else (None, np.zeros(0, dtype=np.int64))
    vi = torch.as_tensor(vi, dtype=torch.long)
    if off < k:  # the subject shows too little beyond the body (tight clothing, one view): the rest on the surface
        more = farthest_point_sampling(tpl, k - off, existing=torch.cat([surface_rest.double(), rest]))
        rest, vi = torch.cat([rest, tpl[more]]), torch.cat([vi, more])
    return HullNodes(rest=rest.float(), vertex=vi, candidates=int(len(cand)), frames=survey.frames, off_body=off,
                     survey=survey)
