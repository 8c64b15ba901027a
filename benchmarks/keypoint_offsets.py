"""Where a person detector puts its keypoints on anny, and how far a project's estimated body fits are from the truth
(issue 51; not a test).

For each (PROJECT, TRUE_MOTION) pair: the detector's 2D keypoints that ingest kept (`ingest/keypoints.npz`) are
triangulated as ingest does (`ingest.estimate.triangulate_detections`, the project's undistorted cameras) and compared
with anny's COCO points (`KeypointsRegressor.coco`) on the true posed body; each keypoint's difference is expressed
in the rest frame of its bone (`ingest.keypoints.KEYPOINT_BONES`: the inverse of the bone's rotation from rest to the
pose, the skinning transform of Eq. 1) and summarised by its per-axis median over the frames where it triangulated.
Across captures the median of the captures' medians (each subject counted once), made left-right symmetric, is
the offset table
`ingest.keypoints.MEDIAPIPE_ANNY_OFFSETS` holds (printed as a Python literal with `--literal`).

With `--fits` it also reports the project's body fits (`ingest/body.npz`) against the truth: the mean distance of
the major joints (`body.joints.major_joints`), each body posed with its OWN shape and joint centres (so a wrong shape
counts: `benchmarks.joint_error` poses both with the fit's shape and the true poses' centres, the pose error alone),
and of anny's COCO points, per group.

    python -m benchmarks.keypoint_offsets PROJECT TRUE_MOTION [PROJECT TRUE_MOTION ...] [--fits] [--literal]
        [--json OUT.json]

TRUE_MOTION: a synth capture's true fits (`CAPTURE/gt/motion.npz` when the capture leaves fits to ingest, else
`CAPTURE/motion.npz`). The projects must have been ingested with detections (`--masks mediapipe` or `--fits
keypoints`). Measured on synth `tight` captures (no garment over the keypoints): docs/own_capture.md.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

GROUPS = {"head": ("nose", "eye", "ear"), "arms": ("shoulder", "elbow", "wrist"), "hips": ("hip",),
          "legs": ("knee", "ankle"), "feet": ("heel", "toe")}


@dataclass(frozen=True)
class CaptureOffsets:
    project: str
    frames: int
    offsets_cm: dict[str, list[float]]  # keypoint -> per-axis median offset in its bone's rest frame, cm
    spread_cm: dict[str, float]  # keypoint -> mean distance of the frames' offsets from that median, cm
    triangulated: dict[str, float]  # keypoint -> share of the frames where it triangulated
    fit_joint_cm: float | None = None  # --fits: the major joints' mean error
    fit_keypoint_cm: dict[str, float] | None = None  # --fits: anny's COCO points' mean error per group (GROUPS)


def _true_points(body, motion, names: tuple[str, ...]):
    """(anny's COCO points [frames, joints, 3], the rotation of each keypoint's bone [frames, joints, 3, 3])."""
    import torch
    from anny.keypoints import KeypointsRegressor

    from avatarctl.ingest.keypoints import KEYPOINT_BONES

    reg = KeypointsRegressor.coco(body.model)
    idx = [list(reg.labels).index(n) for n in names]
    posed = body.pose(motion)
    with torch.no_grad():
        K = reg({"vertices": posed.vertices.double()})[:, idx].numpy()
    bones = [body.joint_names.index(KEYPOINT_BONES[n]) for n in names]
    return K, posed.joint_transforms[:, bones, :3, :3].double().numpy()


def measure(project: Path, true_motion: Path, fits: bool = False) -> CaptureOffsets:
    from avatarctl.body.joints import joint_centres, major_joints, posed_joints, skin_weighted_centroids
    from avatarctl.body.motion import BodyMotion
    from avatarctl.body.registry import load_body_model
    from avatarctl.ingest.estimate import Detections, triangulate_detections
    from avatarctl.io.project_io import load_cameras
    from avatarctl.project import Project

    proj = Project.open(project)
    det = Detections.load(proj.paths.keypoints)
    cams = load_cameras(proj.paths.cameras)
    truth = BodyMotion.load(true_motion)
    if truth.body_model != "anny":
        raise SystemExit(f"{true_motion}: the true fits must be anny's (got {truth.body_model})")
    body = load_body_model("anny")
    have = set(truth.frame_index.tolist())
    frames = [f for f in det.frames if f in have]
    rows = [det.frames.index(f) for f in frames]
    sub = Detections(cams=det.cams, frames=frames, names=det.names, keypoints=det.keypoints[rows],
                     confidence=det.confidence[rows])
    tri = triangulate_detections(sub, [cams[c] for c in det.cams])
    X, valid = tri.X.reshape(len(frames), len(det.names), 3), tri.valid.reshape(len(frames), len(det.names))
    truth = truth.for_frames(frames)
    K, R = _true_points(body, truth, det.names)
    local = np.einsum("fjki,fjk->fji", R, X - K) * 100  # R^T (X - K): the bone's rest frame, cm
    offsets, spread, share = {}, {}, {}
    for j, n in enumerate(det.names):
        v = local[valid[:, j], j]
        share[n] = float(valid[:, j].mean())
        if len(v):
            m = np.median(v, axis=0)
            offsets[n] = [round(float(a), 2) for a in m]
            spread[n] = round(float(np.linalg.norm(v - m, axis=1).mean()), 2)
    joint_cm = kp_cm = None
    if fits:
        est = BodyMotion.load(proj.paths.body)
        fitted = set(est.frame_index.tolist())
        both = [f for f in frames if f in fitted]
        e, t = est.for_frames(both), truth.for_frames(both)
        tpl_e, tpl_t = body.template(e), body.template(t)
        M_e, M_t = body.pose(e).joint_transforms.double(), body.pose(t).joint_transforms.double()
        c_e = joint_centres(M_e, tpl_e.parents, skin_weighted_centroids(tpl_e.vertices, tpl_e.skin_weights).double())
        c_t = joint_centres(M_t, tpl_t.parents, skin_weighted_centroids(tpl_t.vertices, tpl_t.skin_weights).double())
        major = major_joints(tpl_t.skin_weights)
        joint_cm = round(float(100 * (posed_joints(M_e, c_e) - posed_joints(M_t, c_t)).norm(dim=-1)[:, major].mean()),
                         2)
        Ke, _ = _true_points(body, e, det.names)
        Kt, _ = _true_points(body, t, det.names)
        d = np.linalg.norm(Ke - Kt, axis=-1) * 100
        kp_cm = {g: round(float(d[:, [j for j, n in enumerate(det.names) if any(k in n for k in keys)]].mean()), 2)
                 for g, keys in GROUPS.items()}
    return CaptureOffsets(project=str(project), frames=len(frames), offsets_cm=offsets, spread_cm=spread,
                          triangulated=share, fit_joint_cm=joint_cm, fit_keypoint_cm=kp_cm)


def pooled(results: list[CaptureOffsets]) -> dict[str, list[float]]:
    """Per keypoint, the per-axis median of the captures' medians (cm), made left-right symmetric: a left / right
    pair shares y and z (their mean) and mirrors x (anny's x is the subject's left)."""
    names = [n for n in results[0].offsets_cm if all(n in r.offsets_cm for r in results)]
    med = {n: np.median([r.offsets_cm[n] for r in results], axis=0) for n in names}
    for n in names:
        if n.startswith("left_") and "right_" + n[5:] in med:
            left, right = med[n], med["right_" + n[5:]]
            sym = np.array([(left[0] - right[0]) / 2, (left[1] + right[1]) / 2, (left[2] + right[2]) / 2])
            med[n], med["right_" + n[5:]] = sym, sym * [-1, 1, 1]
    return {n: [round(float(a), 2) for a in med[n]] for n in names}


def main(argv: list[str] | None = None) -> tuple[list[CaptureOffsets], dict[str, list[float]]]:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("pairs", nargs="+", help="PROJECT TRUE_MOTION [PROJECT TRUE_MOTION ...]")
    ap.add_argument("--fits", action="store_true", help="also score the projects' body fits against the truth")
    ap.add_argument("--literal", action="store_true", help="print the pooled table as a Python literal (metres)")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    if len(args.pairs) % 2:
        ap.error("give PROJECT TRUE_MOTION pairs")
    results = [measure(Path(p), Path(t), args.fits) for p, t in zip(args.pairs[::2], args.pairs[1::2])]
    pool = pooled(results)
    print("offset of the triangulated keypoint from anny's COCO point in its bone's rest frame (x left, y back, "
          "z up), median over frames, cm [mean spread]")
    print(f"{'keypoint':16s}" + "".join(f"{Path(r.project).name[:22]:>26s}" for r in results) + f"{'pooled':>22s}")
    for n, p in pool.items():
        cells = "".join(f"{str(np.round(r.offsets_cm[n], 1)):>20s} [{r.spread_cm[n]:3.1f}]" for r in results)
        print(f"{n:16s}{cells}{str(np.round(p, 1)):>22s}")
    if args.fits:
        for r in results:
            print(f"{r.project}: body fits against the truth over {r.frames} frames: major joints {r.fit_joint_cm:.2f} "
                  "cm; COCO points " + ", ".join(f"{g} {v:.2f}" for g, v in r.fit_keypoint_cm.items()) + " cm")
    if args.literal:
        from avatarctl.ingest.keypoints import KEYPOINT_BONES

        print("{" + ",\n ".join(f'"{n}": ("{KEYPOINT_BONES[n]}", ({", ".join(f"{a / 100:.3f}" for a in p)}))'
                                for n, p in pool.items()) + "}")
    if args.json is not None:
        args.json.write_text(json.dumps({"captures": [asdict(r) for r in results], "pooled_cm": pool}, indent=2)
                             + "\n")
    return results, pool


if __name__ == "__main__":
    main()
