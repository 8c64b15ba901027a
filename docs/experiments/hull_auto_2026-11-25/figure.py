"""The comparison image: ground truth (masked, over black) and the held-out renders of several runs side by side.

    python docs/experiments/hull_auto_2026-11-25/figure.py OUT.png PROJECT "label=RUN" ... --views 000060_cam04,...

RUN is a fitted project evaluated with `avatarctl eval RUN --save-images` (its eval/novel_view_bbox/renders/).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np


def ground_truth(project: Path, key: str) -> np.ndarray:
    frame, cam = key.split("_")
    img = cv2.imread(str(next((project / "ingest" / "frames" / cam).glob(f"{frame}.*"))))
    mask = cv2.imread(str(next((project / "ingest" / "masks" / cam).glob(f"{frame}.*"))), cv2.IMREAD_GRAYSCALE)
    return (img * (mask[..., None] > 127)).astype(np.uint8)


def labelled(img: np.ndarray, text: str) -> np.ndarray:
    out = img.copy()
    cv2.putText(out, text, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("out", type=Path)
    ap.add_argument("project", type=Path)
    ap.add_argument("runs", nargs="+", help="label=RUN")
    ap.add_argument("--views", required=True, help="comma list of FRAME_CAM, e.g. 000060_cam04")
    a = ap.parse_args()
    runs = [r.rsplit("=", 1) for r in a.runs]  # the label may hold "=", the path does not
    rows = []
    for key in a.views.split(","):
        row = [labelled(ground_truth(a.project, key), f"ground truth {key}")]
        for label, run in runs:
            row.append(labelled(cv2.imread(str(Path(run) / "eval" / "novel_view_bbox" / "renders" / f"{key}.png")),
                                label))
        rows.append(np.concatenate(row, 1))
    a.out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(a.out), np.concatenate(rows, 0))


if __name__ == "__main__":
    main()
