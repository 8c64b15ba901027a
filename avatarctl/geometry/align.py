"""Alignment of point sets: the similarity (Umeyama 1991) a monocular reconstruction is compared with the truth
after (its world frame and scale are its own), and the weighted rigid motion (Kabsch 1976), batched, that fits a body's
root to keypoints and a garment patch's motion to its tracked surface."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Similarity:
    """x -> scale * R @ x + t."""

    scale: float
    R: np.ndarray  # [3, 3] rotation
    t: np.ndarray  # [3]

    def apply(self, x: np.ndarray) -> np.ndarray:
        """[..., 3] -> [..., 3]."""
        return self.scale * x @ self.R.T + self.t


def similarity_align(src: np.ndarray, dst: np.ndarray) -> Similarity:
    """The similarity minimising Σ_i ‖s R src_i + t − dst_i‖² for src, dst [n, 3] (n >= 3, not collinear)."""
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or src.shape[0] < 3:
        raise ValueError(f"similarity_align: src {src.shape} and dst {dst.shape} must be the same [n >= 3, 3]")
    R, _ = rigid_align(src, dst)  # Umeyama's rotation does not depend on the scale
    ms, md = src.mean(0), dst.mean(0)
    a, b = src - ms, dst - md
    scale = float((b * (a @ R.T)).sum() / (a ** 2).sum())  # trace(D S) / the source's variance
    return Similarity(scale=scale, R=R, t=md - scale * R @ ms)


def rigid_align(src: np.ndarray, dst: np.ndarray, w: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The rotation R [..., 3, 3] and translation t [..., 3] minimising Σ_i w_i ‖R src_i + t − dst_i‖² for src, dst
    [..., n, 3] and weights w [..., n] (default 1; three non-collinear weighted points needed), batched over the
    leading axes."""
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    if src.shape != dst.shape or src.ndim < 2 or src.shape[-1] != 3:
        raise ValueError(f"rigid_align: src {src.shape} and dst {dst.shape} must be the same [..., n, 3]")
    w = np.ones(src.shape[:-1]) if w is None else np.broadcast_to(np.asarray(w, np.float64), src.shape[:-1])
    w = w / w.sum(-1, keepdims=True)
    ms, md = (w[..., None] * src).sum(-2), (w[..., None] * dst).sum(-2)
    H = np.swapaxes((src - ms[..., None, :]) * w[..., None], -1, -2) @ (dst - md[..., None, :])  # [..., 3, 3]
    U, _, Vt = np.linalg.svd(H)
    V, Ut = np.swapaxes(Vt, -1, -2), np.swapaxes(U, -1, -2)
    D = np.zeros(H.shape)
    D[..., 0, 0] = D[..., 1, 1] = 1.0
    D[..., 2, 2] = np.sign(np.linalg.det(V @ Ut))
    R = V @ D @ Ut
    return R, md - (R @ ms[..., None])[..., 0]


def aligned_errors(est: np.ndarray, ref: np.ndarray) -> tuple[np.ndarray, Similarity]:
    """Distances [frames, points] of `est` [frames, points, 3] to `ref` after ONE similarity fitted to all frames at
    once (a monocular fit's world and scale are its own; the body's motion over the frames is still compared)."""
    sim = similarity_align(est.reshape(-1, 3), ref.reshape(-1, 3))
    return np.linalg.norm(sim.apply(est) - ref, axis=-1), sim
