"""The SMPL / SMPL-X keypoint fit (`avatarctl/body/smpl_keypoints.py` through `body/fit_keypoints.py`) and its
ingest wiring (`--fits keypoints --body-model smpl|smplx --body-model-path FILE`).

Model files are RANDOM arrays in the official formats (tests/fixtures/smpl.py) whose rest joints form avatarctl's
generic T-pose (y up, facing +z, +x = the subject's left), never real SMPL files."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from avatarctl.cli.app import app
from fixtures.captures import make_easymocap_capture
from fixtures.cli_errors import assert_one_line_error
from fixtures.smpl import write_random_smpl_npz

FRAMES = 2


def _t_pose_file(path: Path, kind: str) -> Path:
    from avatarctl.body import rigs

    names = rigs.SMPL_NAMES if kind == "smpl" else rigs.SMPLX_NAMES
    rest = np.array([rigs.GENERIC_T_POSE[n] for n in names]) * 1.05
    rest += np.random.default_rng(7).normal(0, 0.005, rest.shape)
    rest[:, 1] += 0.25
    return write_random_smpl_npz(path, kind, seed=3, rest_joints=rest)


@pytest.fixture(scope="module")
def model_files(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("models")
    return {k: _t_pose_file(d / f"{k.upper()}_NEUTRAL.npz", k) for k in ("smpl", "smplx")}


def _known_pose(kp, frames: int, seed: int = 0):
    """(rotvecs, R_root, t_root, betas) of a random pose that the keypoints can see: the wrists, collars and feet
    stay at rest (no keypoint pins their rotations), and the body stands z-up about a metre in front of the origin."""
    from avatarctl.body.lbs import axis_angle_to_matrix
    from avatarctl.body.smpl_keypoints import FIT_JOINTS

    g = torch.Generator().manual_seed(seed)
    dt = torch.float64
    rot = 0.3 * torch.randn(frames, len(FIT_JOINTS), 3, generator=g, dtype=dt)
    for n in ("left_wrist", "right_wrist", "left_collar", "right_collar", "left_foot", "right_foot"):
        rot[:, FIT_JOINTS.index(n)] = 0.0
    root = torch.tensor([1.57, 0.0, 0.0], dtype=dt) + 0.3 * torch.randn(frames, 3, generator=g, dtype=dt)
    t = torch.tensor([0.1, 0.0, -0.3], dtype=dt) + 0.05 * torch.randn(frames, 3, generator=g, dtype=dt)
    betas = 0.5 * torch.randn(kp.num_shape, generator=g, dtype=dt)
    return rot, axis_angle_to_matrix(root), t, betas


# ---- the keypoint source -------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["smpl", "smplx"])
def test_keypoint_map_picks_by_geometry(kind, model_files):
    from avatarctl.body.smpl import SmplBody
    from avatarctl.body.smpl_keypoints import NO_SMPL_EYES, smpl_keypoint_map
    from avatarctl.ingest.keypoints import KEYPOINT_NAMES

    body = SmplBody.from_file(model_files[kind], kind=kind)
    km = smpl_keypoint_map(body.data, KEYPOINT_NAMES)
    if kind == "smpl":
        assert km.dropped == {"left_eye": NO_SMPL_EYES, "right_eye": NO_SMPL_EYES}
        assert km.names == tuple(n for n in KEYPOINT_NAMES if not n.endswith("_eye"))
    else:
        assert km.dropped == {} and km.names == KEYPOINT_NAMES
        assert body.joint_names[km.joint[km.names.index("left_eye")]] == "left_eye_smplhf"
    for n in ("left_shoulder", "right_hip", "left_ankle"):
        assert body.joint_names[km.joint[km.names.index(n)]] == n
    v = body.data.v_template
    vert = {n: v[km.vertex[km.names.index(n)]] for n in km.names if km.vertex[km.names.index(n)] >= 0}
    assert set(vert) == {"nose", "left_ear", "right_ear", "left_heel", "right_heel", "left_big_toe", "right_big_toe"}
    head = v[body.data.weights.argmax(1) == body.joint_names.index("head")]
    assert vert["nose"][2] == head[:, 2].max()  # the file faces +z: the nose is the head's most anterior vertex
    assert vert["left_ear"][0] == head[:, 0].max() and vert["right_ear"][0] == head[:, 0].min()  # +x: left
    for s in ("left", "right"):
        assert vert[f"{s}_big_toe"][2] > vert[f"{s}_heel"][2]  # toes in front of the heel
    with pytest.raises(ValueError):
        smpl_keypoint_map(body.data, ("nose",)).names.index("left_eye")


# ---- the fit ---------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["smpl", "smplx"])
def test_fit_recovers_a_known_pose_from_its_keypoints(kind, model_files):
    """The body posed with a known pose, its own keypoints as targets -> the fit's joints and mesh. Bars (measured
    on these files, 2 frames, 300 steps): COCO body joints mean < 1.5 cm, every body joint mean < 2.5 cm (the
    spine's three joints share the torso's bend: 2-3.5 cm there), vertices mean < 4 cm (the random shape
    directions move a keypoint by millimetres per unit beta, so the betas are barely observable and stay near the
    prior; that costs the mesh ~1-2 cm). The untouched start (0 steps) must be far worse."""
    from avatarctl.body.fit_keypoints import KeypointFitConfig, KeypointTargets, fit_keypoints
    from avatarctl.body.smpl import SmplBody
    from avatarctl.body.smpl_keypoints import JOINT_KEYPOINTS, SmplKeypoints
    from avatarctl.ingest.keypoints import KEYPOINT_NAMES

    body = SmplBody.from_file(model_files[kind], kind=kind)
    kp = SmplKeypoints(body, KEYPOINT_NAMES)
    truth = _known_pose(kp, FRAMES)
    with torch.no_grad():
        K, _ = kp.keypoints(*truth)
    pts = np.zeros((FRAMES, len(KEYPOINT_NAMES), 3))
    w = np.zeros((FRAMES, len(KEYPOINT_NAMES)))
    for i, n in enumerate(kp.names):
        pts[:, KEYPOINT_NAMES.index(n)], w[:, KEYPOINT_NAMES.index(n)] = K[:, i].numpy(), 1.0
    targets = KeypointTargets(KEYPOINT_NAMES, pts, w)
    want = body.evaluate(kp.to_motion(*truth))
    coco = [body.joint_names.index(n) for n in JOINT_KEYPOINTS]

    def errors(iters: int) -> tuple[float, float, float]:
        fit = fit_keypoints(kp, targets, KeypointFitConfig(iters=iters))
        assert fit.names == kp.names and fit.motion.body_model == kind
        got = body.evaluate(fit.motion)
        joint = (got.joints[:, :22] - want.joints[:, :22]).norm(dim=-1)  # [frames, 22]
        vert = (got.vertices - want.vertices).norm(dim=-1).mean().item()
        return joint[:, coco].mean().item(), joint.mean().item(), vert

    coco_err, joint_err, vert_err = errors(300)
    assert coco_err < 0.015 and joint_err < 0.025 and vert_err < 0.04, (coco_err, joint_err, vert_err)
    start = errors(0)
    assert start[0] > 4 * coco_err and start[2] > 2 * vert_err, (start, coco_err, vert_err)


@pytest.mark.parametrize("kind", ["smpl", "smplx"])
def test_fitted_motion_file_round_trips(kind, model_files, tmp_path):
    """`to_motion` is the model's own parameters: saved and reloaded, the model gives the fitted keypoints; SMPL-X
    hands and face are zero."""
    from avatarctl.body.motion import BodyMotion
    from avatarctl.body.smpl import SmplBody
    from avatarctl.body.smpl_keypoints import SmplKeypoints, gather_keypoints
    from avatarctl.ingest.keypoints import KEYPOINT_NAMES

    body = SmplBody.from_file(model_files[kind], kind=kind)
    kp = SmplKeypoints(body, KEYPOINT_NAMES)
    truth = _known_pose(kp, 3, seed=1)
    with torch.no_grad():
        K, V = kp.keypoints(*truth)
    kp.to_motion(*truth).save(tmp_path / "m.npz")
    m = BodyMotion.load(tmp_path / "m.npz")
    ev = body.evaluate(m)
    assert (ev.vertices - V).abs().max() < 1e-5
    assert (gather_keypoints(kp.kmap, ev.joints, ev.vertices) - K).abs().max() < 1e-5
    if kind == "smplx":
        assert not m.left_hand_pose.any() and not m.jaw_pose.any() and not m.expression.any()


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    return make_easymocap_capture(tmp_path_factory.mktemp("cap") / "cap", frames=[0, 1, 2], n_cams=3)


def _cli(*args: str):
    return CliRunner().invoke(app, ["ingest", *args])


# ---- ingest wiring ----------------------------------------------------------------------------------------------
def test_missing_model_file_is_one_actionable_line(capture, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "mediapipe", None)  # the model-file error comes first, MediaPipe or not
    proj = tmp_path / "proj"
    for kind in ("smpl", "smplx"):
        line = assert_one_line_error(_cli(str(capture.root), str(proj), "--fits", "keypoints", "--body-model", kind),
                                     proj, f"--body-model {kind} needs the {kind} model file", "--body-model-path")
        assert "MediaPipe" not in line
    assert_one_line_error(_cli(str(capture.root), str(proj), "--fits", "keypoints", "--body-model", "smpl",
                               "--body-model-path", str(tmp_path / "nope.pkl")), proj, "not found", "nope.pkl")


def test_ingest_fits_smpl_to_injected_detections(capture, model_files, tmp_path, monkeypatch):
    """The whole ingest with `--fits keypoints --body-model smpl`: MediaPipe's detector replaced by the SMPL body's
    own keypoints projected into the capture's (undistorted) cameras. The project holds an SMPL motion whose
    joints are the posed ones, and the manifest records the body model and its file."""
    import avatarctl.ingest.estimate as estimate
    import avatarctl.ingest.keypoints as keypoints
    from avatarctl.body.motion import BodyMotion
    from avatarctl.body.smpl import SmplBody
    from avatarctl.body.smpl_keypoints import JOINT_KEYPOINTS, SmplKeypoints
    from avatarctl.geometry.triangulate import project, projection_matrices
    from avatarctl.ingest.undistort import Undistorter

    body = SmplBody.from_file(model_files["smpl"], kind="smpl")
    kp = SmplKeypoints(body, keypoints.KEYPOINT_NAMES)
    truth = _known_pose(kp, len(capture.frames), seed=2)
    with torch.no_grad():
        K, _ = kp.keypoints(*truth)
    want = body.evaluate(kp.to_motion(*truth), with_vertices=False).joints

    def fake_detect(read_view, cams, frames, masks, progress=None, smooth=False):
        pin = [Undistorter.for_camera(c, 1.0).target for c in capture.cameras if c.name in cams]
        x, _ = project(projection_matrices(pin), K.numpy().reshape(-1, 3))  # [frames * joints, cams, 2]
        x = x.reshape(len(frames), len(kp.names), len(cams), 2).transpose(0, 2, 1, 3)
        J = len(keypoints.KEYPOINT_NAMES)
        full = np.full((len(frames), len(cams), J, 2), np.nan)
        conf = np.zeros((len(frames), len(cams), J))
        for i, n in enumerate(kp.names):
            full[:, :, keypoints.KEYPOINT_NAMES.index(n)] = x[:, :, i]
            conf[:, :, keypoints.KEYPOINT_NAMES.index(n)] = 1.0
        return estimate.Detections(cams=list(cams), frames=list(frames), names=keypoints.KEYPOINT_NAMES,
                                   keypoints=full, confidence=conf)

    monkeypatch.setattr(keypoints, "require_mediapipe", lambda *a, **k: None)
    monkeypatch.setattr(estimate, "detect_people", fake_detect)
    proj = tmp_path / "proj"
    res = _cli(str(capture.root), str(proj), "--fits", "keypoints", "--body-model", "smpl", "--body-model-path",
               str(model_files["smpl"]), "--masks", "files", "--keypoint-fit-iters", "300", "--no-contact-sheet")
    assert res.exit_code == 0, res.output
    assert "smpl keypoint fit" in res.output
    manifest = json.loads((proj / "project.json").read_text())
    assert manifest["body_model"] == {"name": "smpl", "path": str(model_files["smpl"].resolve())}
    summary = manifest["stages"][0]["summary"]
    assert summary["fits"] == "keypoints" and summary["body_model"] == "smpl"
    assert summary["estimate"]["body_model"] == "smpl" and summary["estimate"]["fit_error_cm"] < 1.5
    motion = BodyMotion.load(proj / "ingest" / "body.npz")
    assert motion.body_model == "smpl" and list(motion.frame_index) == list(capture.frames)
    got = body.evaluate(motion, with_vertices=False).joints
    coco = [body.joint_names.index(n) for n in JOINT_KEYPOINTS]
    err = (got[:, coco] - want[:, coco]).norm(dim=-1).mean().item()
    assert err < 0.015, err
