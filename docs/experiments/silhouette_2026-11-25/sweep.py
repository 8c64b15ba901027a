"""The keypoint fit with and without its silhouette term, on one set of MediaPipe detections (issue 13).

    python sweep.py CAP REF OUT.json [--weights 0,10,100] [--detections DET.npz] [--frames N] [--limits W]

CAP: a synth capture cut down to intri.yml, extri.yml, images/ (masks, fits and plates withheld, as in
docs/experiments/own_capture_2026-11-25/README.md); REF: the same synth capture ingested with its true masks and fits.
MediaPipe runs once (its keypoints, confidences and masks are cached in DET.npz, since they do not depend on the
fit); then `estimate_fits` (triangulation + anny fit, 400 steps) runs once per silhouette weight, with MediaPipe's
masks as the silhouettes (what `avatarctl ingest CAP P` uses when a capture has no masks), and each fit is compared
with the true fits: anny's `KeypointsRegressor.coco` points (23) per joint group, and the posed meshes (vertex error).
Each fit is saved beside OUT as OUT.w<weight>.npz (a BodyMotion).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

GROUPS = {"head": ("nose", "left_eye", "right_eye", "left_ear", "right_ear"),
          "shoulders": ("left_shoulder", "right_shoulder"), "elbows": ("left_elbow", "right_elbow"),
          "wrists": ("left_wrist", "right_wrist"), "hips": ("left_hip", "right_hip"),
          "knees": ("left_knee", "right_knee"), "ankles": ("left_ankle", "right_ankle")}


def detections(cap: Path, cache: Path):
    from avatarctl.ingest.config import IngestConfig
    from avatarctl.ingest.estimate import Detections, detect_people
    from avatarctl.ingest.pipeline import plan_ingest
    from avatarctl.ingest.undistort import Undistorter

    plan = plan_ingest(IngestConfig(capture=cap, project=Path(tempfile.mkdtemp()) / "p", masks="mediapipe",
                                    fits="keypoints"))
    cams = {c.name: c for c in plan.source.cameras}
    und = {c: Undistorter.for_camera(cams[c], 1.0) for c in plan.cams}
    if cache.exists():
        z = np.load(cache, allow_pickle=False)
        det = Detections(cams=list(plan.cams), frames=list(plan.frames), names=tuple(z["names"]),
                         keypoints=z["keypoints"], confidence=z["confidence"])
        for i, (c, f) in enumerate(z["mask_keys"]):
            det.masks[(str(c), int(f))] = z[f"mask_{i}"].tobytes()
        return plan, und, det
    t0 = time.perf_counter()
    det = detect_people(lambda c, f: und[c].image(plan.source.images.read(c, f)), plan.cams, plan.frames,
                        masks=True)
    print(f"detections: {time.perf_counter() - t0:.0f} s")
    keys = list(det.masks)
    np.savez(cache, names=np.array(det.names), keypoints=det.keypoints, confidence=det.confidence,
             mask_keys=np.array([[c, str(f)] for c, f in keys]),
             **{f"mask_{i}": np.frombuffer(det.masks[k], np.uint8) for i, k in enumerate(keys)})
    return plan, und, det


def compare(body, reg, est, ref) -> dict:
    frames = [int(f) for f in est.frame_index if int(f) in set(int(g) for g in ref.frame_index)]
    est, ref = est.select(est.rows_for(frames)), ref.select(ref.rows_for(frames))
    with torch.no_grad():
        V_est, V_ref = body.pose(est).vertices.double(), body.pose(ref).vertices.double()
        K_est, K_ref = reg({"vertices": V_est}), reg({"vertices": V_ref})
    kerr = 100 * (K_est - K_ref).norm(dim=-1)  # [frames, 23] cm
    labels = list(reg.labels)
    out = {"frames": len(frames), "joint_cm": round(kerr.mean().item(), 3),
           "vertex_cm": round(100 * (V_est - V_ref).norm(dim=-1).mean().item(), 3)}
    for g, names in GROUPS.items():
        out[f"{g}_cm"] = round(kerr[:, [labels.index(n) for n in names]].mean().item(), 2)
    out["feet_cm"] = round(kerr[:, 17:].mean().item(), 2)
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("cap", type=Path)
    ap.add_argument("ref", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--weights", default="0,10,100")
    ap.add_argument("--detections", type=Path)
    ap.add_argument("--frames", type=int, default=0, help="use only the first N frames (0: all)")
    ap.add_argument("--iters", type=int, default=400)
    ap.add_argument("--limits", type=float, default=0.0, help="weight of the joint limits (w_limits; 0: off)")
    a = ap.parse_args()
    from anny.keypoints import KeypointsRegressor

    from avatarctl.body.motion import BodyMotion
    from avatarctl.ingest.estimate import estimate_fits

    plan, und, det = detections(a.cap, a.detections or a.out.with_suffix(".det.npz"))
    if a.frames:
        n = a.frames
        det = type(det)(cams=det.cams, frames=det.frames[:n], names=det.names, keypoints=det.keypoints[:n],
                        confidence=det.confidence[:n], masks={k: v for k, v in det.masks.items() if k[1] in
                                                              set(det.frames[:n])})
    cameras = [und[c].target for c in det.cams]
    ref = BodyMotion.load(a.ref / "ingest" / "body.npz")
    reg = KeypointsRegressor.coco(plan.body.model)
    rows = []
    for w in [float(x) for x in a.weights.split(",")]:
        t0 = time.perf_counter()
        est = estimate_fits(det, cameras, plan.body, a.iters, 30.0, read_mask=det.mask, silhouette_weight=w,
                            limit_weight=a.limits)
        row = {"weight": w, "limits": a.limits, "seconds": round(time.perf_counter() - t0, 1), **compare(plan.body, reg, est.motion, ref),
               "fit_error_cm": round(est.report.fit_error_cm, 3),
               "inside_before": est.report.silhouette_inside_before,
               "inside_after": est.report.silhouette_inside_after}
        print(json.dumps(row), flush=True)
        est.motion.save(a.out.with_suffix(f".w{w:g}.npz"))
        rows.append(row)
    a.out.write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
