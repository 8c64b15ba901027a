"""Hull nodes: put some of the N nodes where the masks show the subject beyond the body (a deviation from the paper,
issue 18; `ModelConfig.hull_nodes`).

The paper places all N nodes on the body surface (farthest point sampling, Sec. 3.1). A loose skirt reaches beyond
every node's support (sigma sqrt(-2 ln eps) = 0.186 m) in a twirl: those rays return background and nothing pulls
a node out there. With `hull_nodes = K > 0`, N - K nodes are sampled on the surface as before and K are placed from
the training masks:

1. for up to `max_frames` training frames, a voxel grid around the posed body (expanded by `margin`) is carved by
   the training views' masks (a voxel is kept when it projects inside the mask of every view that sees it, and at
   least two views see it): the visual hull of that frame;
2. hull voxels farther than `min_dist` from every posed surface node are "off-body";
3. each is mapped to the canonical space with the inverse skinning transform of its nearest posed body vertex
   (Eq. 1 inverted); of the pooled points, only the 5 cm cells that points of at least 15 % of the carved frames fall
   in are kept (one frame's phantom hull volume, or a hem mapped through a swinging leg, is not);
4. K nodes are chosen among them by farthest point sampling, starting from the surface nodes (so they go where the
   surface nodes are not), each skinned like its nearest canonical body vertex. When fewer than K points remain
   (tight clothing; one training view, which carves nothing), the missing nodes go on the surface, farthest from
   the others: the placement is then the paper's.

The node then moves like that vertex (Eq. 3) plus its learned Delta n, like any other node.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from avatarctl.geometry.cameras import Camera
from avatarctl.geometry.triangulate import project, projection_matrices
from avatarctl.model.deformer import farthest_point_sampling


@dataclass(frozen=True)
class HullNodes:
    """K nodes placed off the body (see the module docstring)."""

    rest: torch.Tensor  # [K, 3] canonical positions, metres, float32
    vertex: torch.Tensor  # [K] long: nearest canonical template vertex (its skinning weights are the node's)
    candidates: int  # pooled off-body hull points they were chosen from
    frames: int  # training frames carved
    off_body: int  # nodes placed off the body (< K when the hull showed fewer points: the others on the surface)

    def __post_init__(self) -> None:
        assert self.rest.ndim == 2 and self.rest.shape[1] == 3, f"rest {tuple(self.rest.shape)}"
        assert self.vertex.shape == (self.rest.shape[0],), f"vertex {tuple(self.vertex.shape)}"


def carve(cameras: list[Camera], masks: list[np.ndarray], lo: np.ndarray, hi: np.ndarray, voxel: float
          ) -> np.ndarray:
    """[M, 3] centres of the voxels of the box [lo, hi] (world, metres) inside the visual hull of `masks` (bool
    [H, W] per camera, undistorted images: pinhole projection). A voxel seen by fewer than two cameras is dropped;
    one outside a camera's image is not carved by that camera."""
    axes = [np.arange(a + voxel / 2, b, voxel) for a, b in zip(lo, hi)]
    X = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    keep = np.ones(len(X), dtype=bool)
    seen = np.zeros(len(X), dtype=np.int32)
    px, depth = project(projection_matrices(cameras), X)  # [voxels, cams, 2], [voxels, cams]
    for c, m in enumerate(masks):
        z = depth[:, c]
        u, v = np.round(px[:, c, 0]).astype(np.int64), np.round(px[:, c, 1]).astype(np.int64)
        inside = (z > 0) & (u >= 0) & (v >= 0) & (u < m.shape[1]) & (v < m.shape[0])
        seen += inside
        hit = np.zeros(len(X), dtype=bool)
        hit[inside] = m[v[inside], u[inside]]
        keep &= hit | ~inside
    return X[keep & (seen >= 2)]


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


def place_hull_nodes(capture, body, template, frames: list[int], views: list[str], surface_rest: torch.Tensor,
                     surface_vertex: torch.Tensor, k: int, min_dist: float, *, voxel: float = 0.025,
                     margin: float = 0.35, max_frames: int = 24, min_share: float = 0.15) -> HullNodes:
    """K hull nodes for `capture` (a `ProjectCapture`) from its masks of `frames` x `views` (module docstring).
    `surface_rest` [N - K, 3] / `surface_vertex` [N - K]: the surface nodes already chosen."""
    from scipy.spatial import cKDTree

    from avatarctl.body.lbs import blend_transforms

    use = [frames[i] for i in np.unique(np.linspace(0, len(frames) - 1, min(max_frames, len(frames))).astype(int))]
    motion = capture.motion.select(capture.motion.rows_for(use))
    posed = body.pose(motion)
    W = template.skin_weights.double()
    pooled = []
    for t, frame in enumerate(use):
        V = posed.vertices[t].double()
        lo = V.amin(0).numpy() - margin
        hi = V.amax(0).numpy() + margin
        pts = carve([capture.cameras[v] for v in views], [capture.mask(v, frame) for v in views], lo, hi, voxel)
        Tv = blend_transforms(W, posed.joint_transforms[t:t + 1].double())[0]  # [V, 4, 4]
        nodes = V[surface_vertex].numpy()
        pooled.append(off_body_canonical(pts, V, Tv, nodes, min_dist))
    cand = persistent_cells(pooled, cell=2 * voxel, min_frames=max(2, int(np.ceil(min_share * len(use)))))
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
    return HullNodes(rest=rest.float(), vertex=vi, candidates=int(len(cand)), frames=len(use), off_body=off)
