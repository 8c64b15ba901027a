"""Multi-view triangulation of 2D points: weighted DLT and a robust version that rejects outlier views.

Conventions: pinhole cameras (undistort the 2D points first, or detect on undistorted images), projection matrices
``P = K [R | T]`` [cams, 3, 4] taking world metres to pixels, pixel centres at integer coordinates (OpenCV).

- `triangulate_dlt`: the linear (DLT) triangulation of Hartley & Zisserman, *Multiple View Geometry*, 2nd ed.,
  §12.2: each view contributes the two rows ``x P_3 - P_1`` and ``y P_3 - P_2`` of ``A X = 0``, scaled by its
  weight; X is the right singular vector of A with the smallest singular value.
- `triangulate_robust`: RANSAC (Fischler & Bolles 1981) over every pair of usable views (exhaustive: a capture has
  tens of views, so hundreds of pairs): each pair's DLT point is scored by the confidence-weighted number of views
  that reproject within `threshold_px`; the best hypothesis' inliers are re-triangulated with the weighted DLT.
All functions are batched over any number of points (`points` = joints x frames flattened) with numpy.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations

import numpy as np


def projection_matrices(cameras) -> np.ndarray:
    """[cams, 3, 4] ``K [R | T]`` of pinhole `Camera`s (their distortion is ignored: pass undistorted cameras)."""
    return np.stack([c.K @ np.concatenate([c.R, c.T[:, None]], axis=1) for c in cameras])


def project(P: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project world points X [points, 3] with P [cams, 3, 4] -> (pixels [points, cams, 2], depth [points, cams])."""
    Xh = np.concatenate([X, np.ones_like(X[..., :1])], axis=-1)  # [points, 4]
    x = np.einsum("cij,pj->pci", P, Xh)  # [points, cams, 3]
    z = x[..., 2]
    safe = np.where(np.abs(z) < 1e-12, 1e-12, z)
    return x[..., :2] / safe[..., None], z


def triangulate_dlt(P: np.ndarray, x: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Weighted DLT (H&Z §12.2), batched.

    Args:
        P: [cams, 3, 4] projection matrices. x: [points, cams, 2] pixels. w: [points, cams] weights >= 0
            (0 leaves a view out; each point needs two views with w > 0).
    Returns:
        X [points, 3] world points (NaN where fewer than two views have weight).
    """
    x = np.asarray(x, dtype=np.float64)
    w = np.asarray(w, dtype=np.float64)
    rows_x = x[..., 0:1] * P[None, :, 2, :] - P[None, :, 0, :]  # [points, cams, 4]
    rows_y = x[..., 1:2] * P[None, :, 2, :] - P[None, :, 1, :]
    A = np.concatenate([rows_x, rows_y], axis=1)  # [points, 2 cams, 4]
    A = A / np.maximum(np.linalg.norm(A, axis=-1, keepdims=True), 1e-12)  # unit rows (conditioning, H&Z §4.4)
    A = A * np.concatenate([w, w], axis=1)[..., None]
    _, _, vt = np.linalg.svd(A)
    Xh = vt[:, -1, :]  # [points, 4]
    with np.errstate(divide="ignore", invalid="ignore"):
        X = Xh[:, :3] / Xh[:, 3:4]
    X[(w > 0).sum(axis=1) < 2] = np.nan
    return X


@dataclass(frozen=True)
class Triangulation:
    """Robust triangulation of `points` 2D tracks seen by `cams` cameras."""

    X: np.ndarray  # [points, 3] world metres; NaN where `valid` is False
    valid: np.ndarray  # [points] bool: at least `min_views` inlier views
    inliers: np.ndarray  # [points, cams] bool: views used for X
    error_px: np.ndarray  # [points] mean reprojection error over the inlier views (NaN where not valid)
    candidates: np.ndarray  # [points, cams] bool: views that saw the point with enough confidence

    @property
    def rejected(self) -> np.ndarray:
        """[points, cams] bool: views that saw the point but were rejected as outliers."""
        return self.candidates & ~self.inliers


def triangulate_robust(P: np.ndarray, x: np.ndarray, conf: np.ndarray, threshold_px: float = 8.0,
                       min_conf: float = 0.5, min_views: int = 2) -> Triangulation:
    """RANSAC over view pairs + weighted DLT on the inliers (see the module docstring), batched.

    Args:
        P: [cams, 3, 4]. x: [points, cams, 2] pixels (undistorted). conf: [points, cams] detection confidence in
            [0, 1]; views below `min_conf` are not used.
        threshold_px: reprojection error (px) under which a view is an inlier of a hypothesis.
        min_views: inlier views a point needs to be valid.
    """
    x = np.asarray(x, dtype=np.float64)
    conf = np.nan_to_num(np.asarray(conf, dtype=np.float64))
    n, cams = conf.shape
    cand = (conf >= min_conf) & np.isfinite(x).all(axis=-1)
    x = np.nan_to_num(x)
    best_score = np.full(n, -1.0)
    best_err = np.full(n, np.inf)
    best_in = np.zeros((n, cams), dtype=bool)
    for i, j in combinations(range(cams), 2):
        use = cand[:, i] & cand[:, j]
        if not use.any():
            continue
        w = np.zeros((n, cams))
        w[:, i] = conf[:, i]
        w[:, j] = conf[:, j]
        Xh = triangulate_dlt(P, x[use], w[use])
        px, z = project(P, Xh)
        err = np.linalg.norm(px - x[use], axis=-1)  # [m, cams]
        inl = cand[use] & (err < threshold_px) & (z > 0)
        score = (conf[use] * inl).sum(axis=1)
        mean_err = np.where(inl, err, 0.0).sum(axis=1) / np.maximum(inl.sum(axis=1), 1)
        idx = np.nonzero(use)[0]
        better = (score > best_score[idx] + 1e-9) | ((np.abs(score - best_score[idx]) <= 1e-9)
                                                     & (mean_err < best_err[idx]))
        bi = idx[better]
        best_score[bi], best_err[bi], best_in[bi] = score[better], mean_err[better], inl[better]
    valid = best_in.sum(axis=1) >= min_views
    X = np.full((n, 3), np.nan)
    err = np.full(n, np.nan)
    if valid.any():
        w = np.where(best_in, conf, 0.0)[valid]
        X[valid] = triangulate_dlt(P, x[valid], w)
        px, _ = project(P, X[valid])
        e = np.linalg.norm(px - x[valid], axis=-1)
        err[valid] = np.where(best_in[valid], e, 0.0).sum(axis=1) / best_in[valid].sum(axis=1)
    return Triangulation(X=X, valid=valid, inliers=best_in & valid[:, None], error_px=err, candidates=cand)
