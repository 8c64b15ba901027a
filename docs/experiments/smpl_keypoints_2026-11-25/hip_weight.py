"""The hip convention gap and the SMPL keypoint fit's hip weight (`avatarctl/body/smpl_keypoints.py`, HIP_WEIGHT).

1. The gap, measured on anny (the only body here with both a COCO regressor imitating the annotations and a rig):
   anny's COCO hip keypoint vs its rig's hip joint (`upperleg01.*` head) in the reference pose, over the extremes
   of the phenotype.
2. Its effect on an SMPL fit: a random SMPL file in the official format (tests/fixtures/smpl.py, rest joints in a
   T-pose; never a licensed model) posed with a known pose; its own keypoints are the targets except the hips,
   moved by a gap of that size (1.5 cm medial, 2.5 cm down, 2.0 cm forward in the pelvis frame, 3.5 cm); the fit
   runs with hip weights 1, 0.5, 0.25, 0 and the recovered joints are compared with the truth.

Run from the repository root: `python docs/experiments/smpl_keypoints_2026-11-25/hip_weight.py` (~2 min on 1 core).
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[3]
sys.path.insert(0, str(ROOT / "tests"))
from fixtures.smpl import write_random_smpl_npz  # noqa: E402


def anny_gap() -> None:
    from avatarctl.body.anny_model import AnnyBody
    from avatarctl.body.fit_keypoints import FIT_BONES, AnnyKeypoints
    from avatarctl.ingest.keypoints import KEYPOINT_NAMES

    body = AnnyBody()
    kp = AnnyKeypoints(body, KEYPOINT_NAMES)
    dt = torch.float64
    pose = kp.pose_matrices(torch.zeros(1, len(FIT_BONES), 3, dtype=dt), torch.eye(3, dtype=dt)[None],
                            torch.zeros(1, 3, dtype=dt))
    for i in range(len(body.phenotype_labels)):
        for v in (0.0, 0.5, 1.0):
            ph = torch.full((len(body.phenotype_labels),), 0.5, dtype=dt)
            ph[i] = v
            with torch.no_grad():
                K, _ = kp(pose, ph)
                heads = body.model(pose_parameters=pose, phenotype_kwargs={k: ph[j:j + 1] for j, k in
                                                                           enumerate(body.phenotype_labels)})
            joint = heads["bone_poses"][0, body.joint_names.index("upperleg01.L"), :3, 3].numpy()
            gap = K[0, KEYPOINT_NAMES.index("left_hip")].numpy() - joint  # anny: +x left, -y front, +z up
            print(f"anny {body.phenotype_labels[i]}={v}: COCO hip - hip joint = {np.round(100 * gap, 1)} cm "
                  f"(|gap| {100 * np.linalg.norm(gap):.1f} cm; medial {100 * -gap[0]:.1f}, forward "
                  f"{100 * -gap[1]:.1f}, down {100 * -gap[2]:.1f})")


def smpl_hip_weight() -> None:
    from avatarctl.body import rigs
    from avatarctl.body.fit_keypoints import KeypointFitConfig, KeypointTargets, fit_keypoints
    from avatarctl.body.lbs import axis_angle_to_matrix
    from avatarctl.body.smpl import SmplBody
    from avatarctl.body.smpl_keypoints import FIT_JOINTS, JOINT_KEYPOINTS, SmplKeypoints
    from avatarctl.ingest.keypoints import KEYPOINT_NAMES

    rest = np.array([rigs.GENERIC_T_POSE[n] for n in rigs.SMPL_NAMES]) * 1.05
    rest += np.random.default_rng(7).normal(0, 0.005, rest.shape)
    rest[:, 1] += 0.25
    with tempfile.TemporaryDirectory() as d:
        body = SmplBody.from_file(write_random_smpl_npz(Path(d) / "m.npz", "smpl", seed=3, rest_joints=rest))
    kp = SmplKeypoints(body, KEYPOINT_NAMES)
    F, dt = 3, torch.float64
    g = torch.Generator().manual_seed(5)
    rot = 0.3 * torch.randn(F, len(FIT_JOINTS), 3, generator=g, dtype=dt)
    for n in ("left_wrist", "right_wrist", "left_collar", "right_collar", "left_foot", "right_foot"):
        rot[:, FIT_JOINTS.index(n)] = 0.0
    R = axis_angle_to_matrix(torch.tensor([1.57, 0.0, 0.0], dtype=dt) + 0.3 * torch.randn(F, 3, generator=g, dtype=dt))
    truth = (rot, R, torch.tensor([0.1, 0.0, -0.3], dtype=dt).expand(F, 3), 0.5 * torch.randn(10, generator=g, dtype=dt))
    with torch.no_grad():
        K, _ = kp.keypoints(*truth)
    pts = np.zeros((F, len(KEYPOINT_NAMES), 3))
    w = np.zeros((F, len(KEYPOINT_NAMES)))
    for i, n in enumerate(kp.names):
        pts[:, KEYPOINT_NAMES.index(n)], w[:, KEYPOINT_NAMES.index(n)] = K[:, i].numpy(), 1.0
    for side, sx in (("left", 1.0), ("right", -1.0)):  # the file's axes: +x left, +y up, +z forward
        pts[:, KEYPOINT_NAMES.index(f"{side}_hip")] += np.einsum("fij,j->fi", R.numpy(),
                                                                 np.array([-0.015 * sx, -0.025, 0.020]))
    targets = KeypointTargets(KEYPOINT_NAMES, pts, w)
    want = body.evaluate(kp.to_motion(*truth))
    others = [body.joint_names.index(n) for n in JOINT_KEYPOINTS if not n.endswith("hip")]
    hips = [body.joint_names.index(n) for n in ("left_hip", "right_hip", "pelvis")]
    for hw in (1.0, 0.5, 0.25, 0.0):
        kp.weight = np.array([hw if n.endswith("_hip") else 1.0 for n in kp.names])
        got = body.evaluate(fit_keypoints(kp, targets, KeypointFitConfig(iters=400)).motion)
        e = (got.joints - want.joints).norm(dim=-1)
        print(f"SMPL, hip weight {hw}: other COCO joints {100 * e[:, others].mean():.2f} cm, hips + pelvis "
              f"{100 * e[:, hips].mean():.2f} cm, 22 body joints {100 * e[:, :22].mean():.2f} cm, vertices "
              f"{100 * (got.vertices - want.vertices).norm(dim=-1).mean():.2f} cm", flush=True)


if __name__ == "__main__":
    anny_gap()
    smpl_hip_weight()
