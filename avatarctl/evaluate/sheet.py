"""Comparison sheet: one row per (frame, view): ground truth | render | error heat map, for a person to look at.

The error map is |render - ground truth| averaged over RGB, mapped linearly from 0 (black) to `max_error`
(and above, bright yellow) with OpenCV's "inferno" colour map. With the `bbox` protocol each row shows the SSIM
crop (the projected body box's bounding rectangle) and the PSNR region's outline; with `full` the whole image.
Small crops are enlarged (nearest neighbour) to at least `min_height` pixels so a person can see the detail.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from avatarctl.atomic import write_image


@dataclass(frozen=True)
class SheetRow:
    gt: np.ndarray  # [H, W, 3] float in [0, 1], the region shown (already cropped)
    render: np.ndarray  # [H, W, 3] float in [0, 1]
    region: np.ndarray | None  # [H, W] bool PSNR pixels (outlined), or None
    label: str  # e.g. "frame 12  cam03  PSNR 24.1  SSIM 0.912"


def error_map(render: np.ndarray, gt: np.ndarray, max_error: float = 0.25) -> np.ndarray:
    """[H, W, 3] uint8 heat map of mean-over-RGB absolute error, 0 -> black, >= max_error -> yellow."""
    import cv2

    err = np.abs(np.asarray(render, np.float32) - np.asarray(gt, np.float32)).mean(axis=-1)  # [H, W]
    level = np.clip(err / max_error, 0.0, 1.0)
    bgr = cv2.applyColorMap((level * 255.0 + 0.5).astype(np.uint8), cv2.COLORMAP_INFERNO)
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def _u8(img: np.ndarray) -> np.ndarray:
    return (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def _outline(img: np.ndarray, region: np.ndarray | None) -> np.ndarray:
    import cv2

    if region is None or region.all():
        return img
    out = img.copy()
    contours, _ = cv2.findContours(region.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    cv2.drawContours(out, contours, -1, (0, 255, 0), 1)
    return out


def comparison_sheet(rows: list[SheetRow], dest: str | Path, title: str, max_error: float = 0.25,
                     min_height: int = 200) -> Path:
    """Write the sheet PNG atomically to `dest` and return the path."""
    import cv2

    assert rows, "comparison_sheet needs at least one row"
    panels = []
    for r in rows:
        assert r.gt.shape == r.render.shape, f"gt {r.gt.shape} vs render {r.render.shape}"
        h = r.gt.shape[0]
        scale = max(1, int(np.ceil(min_height / max(h, 1))))
        cells = [_outline(_u8(r.gt), r.region), _outline(_u8(r.render), r.region), error_map(r.render, r.gt, max_error)]
        if scale > 1:
            cells = [cv2.resize(c, (c.shape[1] * scale, c.shape[0] * scale), interpolation=cv2.INTER_NEAREST)
                     for c in cells]
        gap = np.full((cells[0].shape[0], 4, 3), 255, np.uint8)
        strip = np.concatenate([cells[0], gap, cells[1], gap, cells[2]], axis=1)
        panels.append((r.label, strip))
    header = 22
    heading = [title, f"columns: ground truth | render | |error| mean over RGB (black 0 -> yellow {max_error:g}+)"]
    width = max([p.shape[1] for _, p in panels] + [_text_width(t) for t in heading + [lb for lb, _ in panels]])
    blocks = [_text_bar(t, width, header) for t in heading]
    for label, strip in panels:
        body = np.full((strip.shape[0], width, 3), 255, np.uint8)
        body[:, :strip.shape[1]] = strip
        blocks.append(_text_bar(label, width, header))
        blocks.append(body)
    sheet = np.concatenate(blocks, axis=0)
    dest = Path(dest)
    return write_image(dest, cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR))


_FONT_SCALE = 0.42


def _text_width(text: str) -> int:
    import cv2

    (w, _), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, _FONT_SCALE, 1)
    return w + 8


def _text_bar(text: str, width: int, height: int) -> np.ndarray:
    import cv2

    bar = np.full((height, width, 3), 255, np.uint8)
    cv2.putText(bar, text, (4, height - 7), cv2.FONT_HERSHEY_SIMPLEX, _FONT_SCALE, (0, 0, 0), 1, cv2.LINE_AA)
    return bar
