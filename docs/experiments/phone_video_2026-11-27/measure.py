"""Compare the project ingested from ONE synthetic phone video (`avatarctl synth OUT --preset phone`, then
`avatarctl ingest OUT/video.mp4 P`) with the truth the synth wrote under OUT/gt/capture.

    python measure.py P OUT [--out figures.json]

Figures (over the frames P holds; the video's frame k is the capture's frame k):
- joint error: anny's `KeypointsRegressor.coco` (23 points) on the fitted and the true posed meshes, after ONE
  similarity (scale, rotation, translation; Umeyama) fitted to all frames' keypoints at once (the video's world is
  its camera frame, the truth's is the synth world; the scale is the monocular ambiguity); also after a similarity
  per frame (PA-MPJPE, the figure monocular papers give);
- mask IoU: P's MediaPipe masks against the true masks of camera cam00.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("project", type=Path)
    ap.add_argument("synth", type=Path)
    ap.add_argument("--out", type=Path)
    a = ap.parse_args()
    import cv2
    from anny.keypoints import KeypointsRegressor

    from avatarctl.body.anny_model import AnnyBody
    from avatarctl.body.motion import BodyMotion
    from avatarctl.geometry.align import aligned_errors, similarity_align
    from avatarctl.ingest.masks import iou

    truth = a.synth / "gt" / "capture"
    est = BodyMotion.load(a.project / "ingest" / "body.npz")
    ref = BodyMotion.load(truth / "motion.npz")
    frames = [int(f) for f in est.frame_index]
    ref = ref.select(ref.rows_for(frames))
    body = AnnyBody()
    reg = KeypointsRegressor.coco(body.model)
    with torch.no_grad():
        K_est = reg({"vertices": body.pose(est).vertices.double()}).numpy()
        K_ref = reg({"vertices": body.pose(ref).vertices.double()}).numpy()
    err, sim = aligned_errors(K_est, K_ref)  # [frames, 23]
    pa = np.stack([np.linalg.norm(similarity_align(k, r).apply(k) - r, axis=-1) for k, r in zip(K_est, K_ref)])
    train = json.loads((a.project / "ingest" / "split.json").read_text())["train_frames"]
    is_train = np.isin(frames, train)
    out = {"frames_compared": len(frames), "similarity_scale": round(sim.scale, 4),
           "joint_error_cm": round(100 * float(err.mean()), 3),
           "joint_error_cm_train_frames": round(100 * float(err[is_train].mean()), 3),
           "joint_error_cm_test_frames": round(100 * float(err[~is_train].mean()), 3) if (~is_train).any() else None,
           "joint_error_cm_per_frame_similarity": round(100 * float(pa.mean()), 3),
           "joint_error_cm_per_frame": [round(100 * float(e), 2) for e in err.mean(1)],
           "joint_error_cm_per_keypoint": {str(n): round(100 * float(e), 2) for n, e in zip(reg.labels, err.mean(0))}}
    ious = []
    for f in frames:
        m_est = cv2.imread(str(a.project / "ingest" / "masks" / "cam00" / f"{f:06d}.png"), cv2.IMREAD_GRAYSCALE) > 127
        m_ref = cv2.imread(str(truth / "masks" / "cam00" / f"{f:06d}.png"), cv2.IMREAD_GRAYSCALE) > 127
        ious.append(iou(m_est, m_ref))
    out["mask_iou_mean"] = round(float(np.mean(ious)), 4)
    out["mask_iou_min"] = round(float(np.min(ious)), 4)
    out["ingest_summary"] = json.loads((a.project / "project.json").read_text())["stages"][0]["summary"]
    print(json.dumps(out, indent=1))
    if a.out:
        a.out.write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
