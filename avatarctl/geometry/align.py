"""Similarity alignment of two point sets (Umeyama 1991): what a monocular reconstruction is compared with the
truth after (its world frame and scale are its own)."""

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
    ms, md = src.mean(0), dst.mean(0)
    a, b = src - ms, dst - md
    U, S, Vt = np.linalg.svd(b.T @ a / len(src))
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ d @ Vt
    scale = float(np.trace(np.diag(S) @ d) / (a ** 2).sum(1).mean())
    return Similarity(scale=scale, R=R, t=md - scale * R @ ms)


def aligned_errors(est: np.ndarray, ref: np.ndarray) -> tuple[np.ndarray, Similarity]:
    """Distances [frames, points] of `est` [frames, points, 3] to `ref` after ONE similarity fitted to all frames at
    once (a monocular fit's world and scale are its own; the body's motion over the frames is still compared)."""
    sim = similarity_align(est.reshape(-1, 3), ref.reshape(-1, 3))
    return np.linalg.norm(sim.apply(est) - ref, axis=-1), sim
