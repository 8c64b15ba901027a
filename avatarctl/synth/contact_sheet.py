"""The capture's contact sheet: a grid of frames (rows) x views (columns) with labels, for a person to look at."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from avatarctl.atomic import write_image
from avatarctl.synth.config import SynthConfig

MAX_VIEWS = 4
TILE = 192


def contact_sheet(path: Path, tiles: dict[tuple[int, int], np.ndarray], frames: list[int], names: list[str],
                  hem_radius: np.ndarray, config: SynthConfig) -> None:
    """Write `path` (PNG). tiles[(frame, cam)] = RGB uint8 [H, W, 3]; rows are `frames`, columns up to 4 views
    spread around the ring. Each row is labelled with its frame, segment and hem radius (metres)."""
    import cv2

    views = np.unique(np.linspace(0, len(names) - 1, min(MAX_VIEWS, len(names))).round().astype(int)).tolist()
    label_h = 18
    rows = []
    for f in frames:
        seg = "train" if f < config.train_frames else "test"
        cells = []
        for c in views:
            tile_w = max(1, round(TILE * config.image_width / config.size))
            img = tiles.get((f, c))
            if img is None:
                img = np.zeros((TILE, tile_w, 3), np.uint8)
            img = cv2.resize(img, (tile_w, TILE), interpolation=cv2.INTER_AREA if img.shape[0] > TILE
                             else cv2.INTER_NEAREST)
            cell = np.full((TILE + label_h, tile_w, 3), 255, np.uint8)
            cell[label_h:] = img
            cv2.putText(cell, f"f{f:04d} {seg} {names[c]} hem {hem_radius[f]:.2f}m", (3, 13),
                        cv2.FONT_HERSHEY_SIMPLEX, 0.36, (0, 0, 0), 1, cv2.LINE_AA)
            cells.append(cell)
            cells.append(np.full((TILE + label_h, 2, 3), 255, np.uint8))
        rows.append(np.concatenate(cells[:-1], axis=1))
        rows.append(np.full((2, rows[-1].shape[1], 3), 255, np.uint8))
    sheet = np.concatenate(rows[:-1], axis=0)
    write_image(path, np.ascontiguousarray(sheet[..., ::-1]))
