"""Figure: MediaPipe's 2D keypoints (yellow), the fitted anny keypoints (red) and the true ones (green) projected
into a few views of one frame, plus the estimated mask outline (cyan) and the true one (white).

    python keypoint_figure.py EST_PROJECT REF_PROJECT FRAME OUT.jpg [--views cam00,cam03,cam06,cam09] [--scale 2]

Needs MediaPipe (the capture extra): the detections are re-run on the project's undistorted frames.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("est", type=Path)
    ap.add_argument("ref", type=Path)
    ap.add_argument("frame", type=int)
    ap.add_argument("out", type=Path)
    ap.add_argument("--views", default="cam00,cam03,cam06,cam09")
    ap.add_argument("--scale", type=int, default=2)
    a = ap.parse_args()
    import cv2
    from anny.keypoints import KeypointsRegressor

    from avatarctl.body.anny_model import AnnyBody
    from avatarctl.body.motion import BodyMotion
    from avatarctl.io.project_io import load_cameras
    from avatarctl.ingest.keypoints import KEYPOINT_NAMES, PoseDetector

    cams = load_cameras(a.est / "ingest" / "cameras.json")
    body = AnnyBody()
    reg = KeypointsRegressor.coco(body.model)
    idx = [list(reg.labels).index(n) for n in KEYPOINT_NAMES]
    K = {}
    for tag, proj in (("est", a.est), ("ref", a.ref)):
        m = BodyMotion.load(proj / "ingest" / "body.npz")
        m = m.select(m.rows_for([a.frame]))
        with torch.no_grad():
            K[tag] = reg({"vertices": body.pose(m).vertices.double()})[0, idx].numpy()
    tiles = []
    s = a.scale
    for v in a.views.split(","):
        rgb = cv2.imread(str(a.est / "ingest" / "frames" / v / f"{a.frame:06d}.jpg"))[..., ::-1].copy()
        with PoseDetector(masks=False) as det:
            d = det(rgb)
        img = cv2.resize(rgb, None, fx=s, fy=s, interpolation=cv2.INTER_NEAREST)
        for proj, colour in ((a.est, (40, 230, 255)), (a.ref, (255, 255, 255))):
            mask = cv2.imread(str(proj / "ingest" / "masks" / v / f"{a.frame:06d}.png"), cv2.IMREAD_GRAYSCALE) > 127
            mask = cv2.resize(mask.astype(np.uint8), None, fx=s, fy=s, interpolation=cv2.INTER_NEAREST)
            contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
            cv2.drawContours(img, contours, -1, colour, 1)
        for pts, colour, r in ((cams[v].project(K["ref"], distort=False), (40, 220, 40), 4),
                               (cams[v].project(K["est"], distort=False), (255, 40, 40), 3),
                               (d.keypoints, (255, 230, 40), 2)):
            for x, y in pts[np.isfinite(pts).all(axis=1)]:
                cv2.circle(img, (int(round((x + 0.5) * s - 0.5)), int(round((y + 0.5) * s - 0.5))), r, colour, -1,
                           cv2.LINE_AA)
        cv2.putText(img, f"{v} f{a.frame}", (6, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 1, cv2.LINE_AA)
        tiles.append(img)
    cv2.imwrite(str(a.out), np.concatenate(tiles, axis=1)[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 90])


if __name__ == "__main__":
    main()
