"""The visual hull of a set of masks (space carving on a voxel grid): the hull nodes' survey (fit/hull_nodes.py) and
the garment tracker's reference surface (fit/garment_track.py)."""

from __future__ import annotations

import numpy as np

from avatarctl.geometry.cameras import Camera
from avatarctl.geometry.triangulate import project, projection_matrices


def carve(cameras: list[Camera], masks: list[np.ndarray], lo: np.ndarray, hi: np.ndarray, voxel: float,
          explained: list[np.ndarray] | None = None) -> np.ndarray:
    """[M, 3] centres of the voxels of the box [lo, hi] (world, metres) inside the visual hull of `masks` (bool
    [H, W] per camera, undistorted images: pinhole projection). A voxel seen by fewer than two cameras is dropped;
    one outside a camera's image is not carved by that camera. With `explained` (bool [H, W] per camera: the
    pixels the body accounts for), a voxel is kept only when some camera puts it on a mask pixel not explained
    (phantom volumes of a few views project onto the body in every view)."""
    axes = [np.arange(a + voxel / 2, b, voxel) for a, b in zip(lo, hi)]
    X = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    keep = np.ones(len(X), dtype=bool)
    seen = np.zeros(len(X), dtype=np.int32)
    shows = np.zeros(len(X), dtype=bool) if explained is not None else np.ones(len(X), dtype=bool)
    px, depth = project(projection_matrices(cameras), X)  # [voxels, cams, 2], [voxels, cams]
    for c, m in enumerate(masks):
        z = depth[:, c]
        u, v = np.round(px[:, c, 0]).astype(np.int64), np.round(px[:, c, 1]).astype(np.int64)
        inside = (z > 0) & (u >= 0) & (v >= 0) & (u < m.shape[1]) & (v < m.shape[0])
        seen += inside
        hit = np.zeros(len(X), dtype=bool)
        hit[inside] = m[v[inside], u[inside]]
        keep &= hit | ~inside
        if explained is not None:
            shows[inside] |= m[v[inside], u[inside]] & ~explained[c][v[inside], u[inside]]
    return X[keep & (seen >= 2) & shows]
