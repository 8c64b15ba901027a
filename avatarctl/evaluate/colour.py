"""The per-camera colour transform (issue 51: cameras that disagree in exposure and white balance), stated once.

A camera c records the subject's colour x as gain_c * x + offset_c, per channel (3 gains + 3 offsets: exposure and
white balance act per channel of the sensor, a diagonal von Kries transform; a full 3x3 would also let the transform
trade colour with the avatar's albedo between cameras, which 3 or 4 training cameras do not pin down). The transform
acts on the foreground only: a pixel rendered over the training background bg with opacity alpha holds the
premultiplied colour f = rgb - (1 - alpha) bg, and camera c sees

    gain_c * f + alpha * offset_c + (1 - alpha) * bg                                   (`apply_colour`)

so the background (a fixed colour, not a photograph: the target is rgb * mask + bg * (1 - mask)) never changes.
Used by the fit (`model/colour.py`: learned per training camera, torch tensors) and by `eval` (`estimate_colour`: a
held-out camera's transform from half of each image, NeRF-W's protocol; numpy). The arithmetic works on numpy arrays
and torch tensors alike.
"""

from __future__ import annotations

from typing import Any

import numpy as np


def apply_colour(rgb: Any, alpha: Any, background: Any, gain: Any, offset: Any) -> Any:
    """rgb [..., 3] composited over `background` [3] with opacity alpha [...] -> the same pixels with the
    foreground's colour transformed by gain, offset ([3], or [..., 3] per pixel); see the module docstring."""
    bg = (1 - alpha)[..., None] * background  # [..., 3]
    return gain * (rgb - bg) + alpha[..., None] * offset + bg


def estimate_colour(rgb: np.ndarray, alpha: np.ndarray, gt: np.ndarray, background: np.ndarray, mask: np.ndarray,
                    ridge: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
    """The transform (gain [3], offset [3] = 0) of a camera's exposure and white balance, from the `mask` pixels:
    per channel the ratio of the summed foreground colours where the render is opaque (alpha >= 0.5), gain_k =
    (sum t_k + r) / (sum f_k + r) with r = `ridge` times the pixel count (identity without such pixels). rgb, gt [H, W, 3], alpha [H, W], mask [H, W]
    bool; float64 sums. Why a ratio and no offset: a held-out render is blurrier than its photograph and a little
    misaligned, and a least-squares fit of gain and offset regresses towards the mean colour (on 300 s fits of synth
    realistic and its clean twin, `python -m benchmarks.realistic_capture OUT --only clean,realistic --colour`, it
    found gains of 0.67-0.80 for a camera 1.19x brighter, and scored the realistic capture's right halves 0.8 dB
    below the plain render); exposure and white balance are gains (the module docstring)."""
    m = np.asarray(mask, bool) & (np.asarray(alpha) >= 0.5)  # where the render holds the subject
    a = alpha[m].astype(np.float64)  # [n]
    bg = np.asarray(background, np.float64).reshape(3)
    f = rgb[m].astype(np.float64) - (1 - a)[:, None] * bg  # [n, 3] premultiplied foreground
    t = gt[m].astype(np.float64) - (1 - a)[:, None] * bg  # what the transformed foreground must match
    lam = ridge * max(int(m.sum()), 1)
    return (t.sum(0) + lam) / (f.sum(0) + lam), np.zeros(3)


def halves(mask: np.ndarray, crop: tuple[int, int, int, int]) -> tuple[np.ndarray, np.ndarray]:
    """(left, right) halves of the evaluation `mask` [H, W], split at the middle column of its bounding rectangle
    `crop` (x0, y0, x1, y1): NeRF-W's held-out protocol fits the appearance on the left half, scores the right."""
    x0, _, x1, _ = crop
    cols = np.arange(mask.shape[1])[None, :]
    mid = (x0 + x1) // 2
    return mask & (cols < mid), mask & (cols >= mid)
