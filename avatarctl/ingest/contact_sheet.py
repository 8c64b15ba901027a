"""``ingest/contact_sheet.png``: undistorted frames with the posed body mesh overlaid, to check alignment by eye.

Each tile: the undistorted frame, the projected body mesh silhouette tinted red (35 %), the mask outline in green,
the detected 2D keypoints in yellow (when ingest estimated the fits or masks), labelled ``<camera> f<frame>``. Rows are frames, columns cameras (one camera, a video: the frames in one row).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from avatarctl.atomic import write_image


@dataclass(frozen=True)
class Tile:
    cam: str
    frame: int
    rgb: np.ndarray  # [H, W, 3] uint8, undistorted
    mask: np.ndarray  # [H, W] bool
    body: np.ndarray  # [H, W] bool, projected posed mesh
    points: np.ndarray | None = None  # [joints, 2] detected keypoints (pixels; NaN: not found), or None


def pick(items: list, n: int) -> list:
    """Up to `n` items spread evenly over `items` (first and last included)."""
    if len(items) <= n:
        return list(items)
    idx = np.unique(np.round(np.linspace(0, len(items) - 1, n)).astype(int))
    return [items[i] for i in idx]


def render_tile(t: Tile, width: int) -> np.ndarray:
    import cv2

    img = t.rgb.astype(np.float32)
    red = np.array([255, 40, 40], np.float32)
    img[t.body] = 0.65 * img[t.body] + 0.35 * red
    img = img.clip(0, 255).astype(np.uint8)
    contours, _ = cv2.findContours(t.mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    cv2.drawContours(img, contours, -1, (40, 255, 40), max(1, t.rgb.shape[1] // 300))
    if t.points is not None:
        r = max(1, t.rgb.shape[1] // 150)
        for x, y in t.points[np.isfinite(t.points).all(axis=1)]:
            cv2.circle(img, (int(round(x)), int(round(y))), r, (255, 230, 40), -1, cv2.LINE_AA)
    h = int(round(img.shape[0] * width / img.shape[1]))
    img = cv2.resize(img, (width, h), interpolation=cv2.INTER_AREA)
    cv2.putText(img, f"{t.cam} f{t.frame}", (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
    return img


def write_contact_sheet(path, tiles: list[Tile], cams: list[str], frames: list[int], width: int = 256) -> None:
    """Grid of tiles (rows = frames, columns = cams; one camera: the frames side by side); missing cells stay black.
    Written atomically."""
    import cv2

    by = {(t.cam, t.frame): render_tile(t, width) for t in tiles}
    h = max(im.shape[0] for im in by.values())
    cells = [[(c, f) for c in cams] for f in frames] if len(cams) > 1 else [[(cams[0], f) for f in frames]]
    sheet = np.zeros((h * len(cells), width * len(cells[0]), 3), np.uint8)
    for r, row in enumerate(cells):
        for c, key in enumerate(row):
            im = by.get(key)
            if im is not None:
                sheet[r * h:r * h + im.shape[0], c * width:(c + 1) * width] = im
    write_image(path, cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR))
