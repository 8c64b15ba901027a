"""Rendered images -> PNG files (render frames, eval `--save-images`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from avatarctl.atomic import write_image


def to_uint8(rgb: np.ndarray) -> np.ndarray:
    """float in [0, 1] -> uint8, rounded (values outside [0, 1] are clipped)."""
    return (np.clip(rgb, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def write_png(dest: Path, rgb: np.ndarray, alpha: np.ndarray | None) -> None:
    """[H, W, 3] float in [0, 1] (+ [H, W] alpha for RGBA with straight colour) -> PNG."""
    import cv2

    img = to_uint8(rgb)
    if alpha is None:
        bgr = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    else:
        a = np.clip(alpha, 0.0, 1.0)[..., None]
        straight = np.where(a > 1e-4, rgb / np.maximum(a, 1e-4), 0.0)  # rendered over black = premultiplied
        rgba = np.concatenate([to_uint8(straight), to_uint8(a)], axis=-1)
        bgr = cv2.cvtColor(rgba, cv2.COLOR_RGBA2BGRA)
    write_image(dest, bgr)
