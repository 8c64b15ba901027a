"""benchmarks/keypoint_offsets.py on a synthetic project: detections that are anny's COCO points moved by known
offsets in their bones' frames (projected into six cameras, no noise) give those offsets back; fits equal to the truth
score zero; the pooled table is left-right symmetric."""

from __future__ import annotations

import json

import numpy as np
import pytest


def test_keypoint_offsets_recovers_known_offsets(tmp_path, capsys):
    import roma
    import torch

    from avatarctl.body.anny_model import AnnyBody
    from avatarctl.body.fit_keypoints import FIT_BONES, AnnyKeypoints
    from avatarctl.geometry.triangulate import project, projection_matrices
    from avatarctl.ingest.estimate import Detections
    from avatarctl.ingest.keypoints import KEYPOINT_BONES, KEYPOINT_NAMES
    from avatarctl.io.project_io import save_cameras
    from avatarctl.project import BodyModelRef, Project, SourceRef
    from benchmarks.keypoint_offsets import main
    from fixtures.captures import ring_cameras

    body = AnnyBody()
    offsets = {"left_hip": (-0.01, -0.01, 0.03), "right_hip": (0.01, -0.01, 0.03), "left_ear": (-0.03, -0.02, 0.01),
               "right_ear": (0.03, -0.02, 0.01), "right_knee": (0.013, 0.006, 0.024)}
    kp = AnnyKeypoints(body, KEYPOINT_NAMES, offsets={n: (KEYPOINT_BONES[n], o) for n, o in offsets.items()})
    g = torch.Generator().manual_seed(5)
    rot = 0.3 * torch.randn(4, len(FIT_BONES), 3, generator=g, dtype=torch.float64)
    R = roma.rotvec_to_rotmat(0.3 * torch.randn(4, 3, generator=g, dtype=torch.float64))
    t = torch.zeros(4, 3, dtype=torch.float64)
    shape = torch.zeros(6, dtype=torch.float64)
    with torch.no_grad():
        K, _ = kp.keypoints(rot, R, t, shape)
    truth = kp.to_motion(rot, R, t, shape)
    cams = [c.pinhole() for c in ring_cameras(6, 256)]
    x, _ = project(projection_matrices(cams), K.numpy().reshape(-1, 3))
    x = x.reshape(4, len(KEYPOINT_NAMES), 6, 2).transpose(0, 2, 1, 3).copy()
    proj = Project.create(tmp_path / "P", BodyModelRef(name="anny"), SourceRef(str(tmp_path), "synthetic", "0", 0))
    save_cameras(proj.paths.cameras, cams)
    truth.save(proj.paths.body)
    Detections(cams=[c.name for c in cams], frames=[0, 1, 2, 3], names=KEYPOINT_NAMES, keypoints=x,
               confidence=np.ones(x.shape[:3])).save(proj.paths.keypoints)
    truth.save(tmp_path / "truth.npz")

    results, pool = main([str(proj.root), str(tmp_path / "truth.npz"), "--fits", "--literal",
                          "--json", str(tmp_path / "o.json")])
    (r,) = results
    for n in KEYPOINT_NAMES:
        want = np.array(offsets.get(n, (0.0, 0.0, 0.0))) * 100
        np.testing.assert_allclose(r.offsets_cm[n], want, atol=0.05)  # cm: float32 pixels, DLT
        assert r.triangulated[n] == 1.0
    assert r.fit_joint_cm == pytest.approx(0.0, abs=1e-3) and max(r.fit_keypoint_cm.values()) < 1e-3
    # pooled: the knee pair made symmetric (x mirrored, y and z averaged with the left knee's zero)
    np.testing.assert_allclose(pool["right_knee"], [0.65, 0.3, 1.2], atol=0.05)
    np.testing.assert_allclose(pool["left_knee"], [-0.65, 0.3, 1.2], atol=0.05)
    out = capsys.readouterr().out
    assert '"left_hip": ("pelvis.L", (-0.010, -0.010, 0.030))' in out and "major joints 0.00 cm" in out
    assert json.loads((tmp_path / "o.json").read_text())["pooled_cm"]["left_ear"] == pytest.approx([-3.0, -2.0, 1.0],
                                                                                                  abs=0.05)
