"""Overlay of the fits with and without the silhouette term on the masks they were fitted to.

    python overlay.py CAP REF SWEEP_OUT FRAME OUT.jpg     # SWEEP_OUT: the OUT.json of sweep.py (its .det.npz, .w*.npz)

Per view (the first four cameras): MediaPipe's mask (grey), the true body's silhouette outline (green), the
projected vertices of the fit without the term (red) and with λ_sil = 10 (blue).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch


def main() -> None:
    import cv2

    from avatarctl.body.motion import BodyMotion
    from avatarctl.geometry.silhouette import project_vertices, rasterize_silhouette

    sys.path.insert(0, str(Path(__file__).parent))
    from sweep import detections

    cap, ref, out_json, frame, out = Path(sys.argv[1]), Path(sys.argv[2]), Path(sys.argv[3]), int(sys.argv[4]), sys.argv[5]
    plan, und, det = detections(cap, out_json.with_suffix(".det.npz"))
    body = plan.body

    def verts(path: Path) -> np.ndarray:
        m = BodyMotion.load(path)
        with torch.no_grad():
            return body.pose(m.select(m.rows_for([frame]))).vertices[0].numpy()

    v_true, v0, v10 = verts(ref / "ingest" / "body.npz"), verts(out_json.with_suffix(".w0.npz")), \
        verts(out_json.with_suffix(".w10.npz"))
    faces = body.faces().cpu().numpy()
    tiles = []
    for c in det.cams[:4]:
        cam = und[c].target
        img = np.full((cam.height, cam.width, 3), 40, np.uint8)
        img[det.mask(c, frame)] = 110
        sil = rasterize_silhouette(cam, v_true, faces).astype(np.uint8)
        contours, _ = cv2.findContours(sil, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        cv2.drawContours(img, contours, -1, (0, 220, 0), 1)
        for v, col in ((v0, (230, 40, 40)), (v10, (60, 120, 255))):
            uv, _ = project_vertices(cam, v[::7])
            for x, y in np.round(uv).astype(int):
                if 0 <= x < cam.width and 0 <= y < cam.height:
                    img[y, x] = col
        tiles.append(cv2.resize(img, (cam.width * 2, cam.height * 2), interpolation=cv2.INTER_NEAREST))
    cv2.imwrite(out, cv2.cvtColor(np.concatenate(tiles, axis=1), cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 85])


if __name__ == "__main__":
    main()
