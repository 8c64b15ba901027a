"""Compare a project ingested with estimated masks / fits (`--masks mediapipe --fits keypoints`) with the project
ingested from the same synth capture with its true masks and fits (`--masks files --fits files`).

    python measure.py EST_PROJECT REF_PROJECT [--out figures.json]

Figures (over the frames both projects hold):
- mask IoU: estimated vs true undistorted masks, mean over (camera, frame) views;
- keypoint (joint) error: anny's `KeypointsRegressor.coco` (23 points) on both posed meshes, mean distance (cm);
- vertex error: mean distance between the posed anny meshes (same topology, cm);
- the ingest summary of the estimated project (detections, reprojection error, rejected views, fit error).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("est", type=Path)
    ap.add_argument("ref", type=Path)
    ap.add_argument("--out", type=Path)
    a = ap.parse_args()
    import cv2
    from anny.keypoints import KeypointsRegressor

    from avatarctl.body.anny_model import AnnyBody
    from avatarctl.body.motion import BodyMotion
    from avatarctl.ingest.masks import iou

    est = BodyMotion.load(a.est / "ingest" / "body.npz")
    ref = BodyMotion.load(a.ref / "ingest" / "body.npz")
    frames = [int(f) for f in est.frame_index if int(f) in set(int(g) for g in ref.frame_index)]
    est, ref = est.select(est.rows_for(frames)), ref.select(ref.rows_for(frames))
    body = AnnyBody()
    reg = KeypointsRegressor.coco(body.model)
    out = {}
    with torch.no_grad():
        V_est, V_ref = body.pose(est).vertices.double(), body.pose(ref).vertices.double()
        K_est, K_ref = reg({"vertices": V_est}), reg({"vertices": V_ref})
    kerr = (K_est - K_ref).norm(dim=-1)  # [frames, 23]
    out["frames_compared"] = len(frames)
    out["joint_error_cm"] = round(100 * kerr.mean().item(), 3)
    out["joint_error_cm_per_keypoint"] = {str(n): round(100 * float(e), 2) for n, e in zip(reg.labels, kerr.mean(0))}
    out["joint_error_cm_coco17"] = round(100 * kerr[:, :17].mean().item(), 3)
    out["vertex_error_cm"] = round(100 * (V_est - V_ref).norm(dim=-1).mean().item(), 3)
    out["phenotype_est"] = dict(zip(est.phenotype_labels, np.round(est.phenotype, 3).tolist()))
    out["phenotype_ref"] = dict(zip(ref.phenotype_labels, np.round(ref.phenotype, 3).tolist()))
    ious = []
    for cam_dir in sorted((a.est / "ingest" / "masks").iterdir()):
        for f in frames:
            m_est = cv2.imread(str(cam_dir / f"{f:06d}.png"), cv2.IMREAD_GRAYSCALE) > 127
            m_ref = cv2.imread(str(a.ref / "ingest" / "masks" / cam_dir.name / f"{f:06d}.png"), cv2.IMREAD_GRAYSCALE) > 127
            ious.append(iou(m_est, m_ref))
    out["mask_iou_mean"] = round(float(np.mean(ious)), 4)
    out["mask_iou_min"] = round(float(np.min(ious)), 4)
    manifest = json.loads((a.est / "project.json").read_text())
    out["ingest_summary"] = manifest["stages"][0]["summary"]
    print(json.dumps(out, indent=1))
    if a.out:
        a.out.write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
