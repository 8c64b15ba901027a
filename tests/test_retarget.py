"""Motion retargeting (`avatarctl.body.skeleton`, `rigs`, `retarget`, `rig_motion`): SMPL -> anny bone directions,
feet on the floor, the hip-centre track, and the forward kinematics every rig shares checked against the body
models' own (`SmplBody.joints`, anny's forward pass)."""

from __future__ import annotations

import numpy as np
import pytest

from avatarctl.body import rig_motion
from avatarctl.body.motion import BodyMotion
from avatarctl.body.registry import load_body_model
from avatarctl.body.retarget import direction_errors, floor_errors, match_joints, retarget
from avatarctl.body.skeleton import SkeletonMotion, rotation_angle
from fixtures.smpl import grounded_smpl_walk, write_random_smpl_npz, write_t_pose_smpl_npz


def _random_smpl_motion(frames: int = 6, seed: int = 0) -> BodyMotion:
    rng = np.random.default_rng(seed)
    return BodyMotion(body_model="smpl", frame_index=np.arange(frames), global_orient=rng.normal(0, 0.4, (frames, 3)),
                      body_pose=rng.normal(0, 0.35, (frames, 69)), transl=rng.normal(0, 0.3, (frames, 3)),
                      betas=rng.normal(0, 1, 10))


@pytest.fixture(scope="module")
def anny_skeleton():
    return rig_motion.skeleton_of("anny")


def test_skeleton_fk_matches_the_smpl_model(tmp_path):
    """The shared FK (local rotations about rest heads, root at J_0 + transl) reproduces SmplBody's joints."""
    path = write_random_smpl_npz(tmp_path / "smpl.npz", "smpl", seed=3)
    m = _random_smpl_motion()
    sm = rig_motion.to_skeleton_motion(m, rig_motion.skeleton_of("smpl", m, path))
    joints = load_body_model("smpl", path).joints(m).numpy()
    assert np.abs(sm.joint_positions() - joints).max() < 1e-5
    back = rig_motion.to_body_motion(sm, "smpl", m)  # and back to axis-angle parameters
    assert np.allclose(back.body_pose, m.body_pose, atol=1e-5) and np.allclose(back.transl, m.transl, atol=1e-5)


@pytest.mark.anny
def test_random_smpl_poses_on_anny_keep_every_bone_direction(tmp_path, anny_skeleton):
    """Random poses of a random SMPL model file (official npz format), retargeted shape-aware onto anny: each mapped
    bone (joint -> its primary child) points where SMPL's does, measured on anny's own forward pass."""
    from avatarctl.body.anny_model import AnnyBody

    path = write_random_smpl_npz(tmp_path / "smpl.npz", "smpl", seed=1)
    m = _random_smpl_motion(frames=8, seed=2)
    src = rig_motion.to_skeleton_motion(m, rig_motion.skeleton_of("smpl", m, path))
    out, report = retarget(src, anny_skeleton)
    assert len(report.mapped) == 24 and report.dropped == ()
    # our FK of the result is anny's: heads of anny's bone poses for the written pose parameters
    bm = rig_motion.to_body_motion(out, "anny")
    heads = AnnyBody().run(bm)["bone_poses"][..., :3, 3].numpy()
    assert np.abs(heads - out.joint_positions()).max() < 1e-5
    err = direction_errors(src, out)
    assert len(err.bones) == 19  # pelvis, spine x3, legs x6, arms x8 incl. wrist -> palm, neck
    assert err.degrees.mean() <= 5.0 and err.degrees.max() < 0.01  # exact by construction, to float precision
    assert err.rest_degrees.mean() > 20.0  # not vacuous: the random rest skeletons disagree a lot


@pytest.mark.anny
def test_walk_on_anny_keeps_feet_on_the_floor_and_the_hip_track(tmp_path, anny_skeleton):
    path = write_t_pose_smpl_npz(tmp_path / "tpose.npz")
    m = grounded_smpl_walk(path)
    src = rig_motion.to_skeleton_motion(m, rig_motion.skeleton_of("smpl", m, path))
    out, report = retarget(src, anny_skeleton)
    assert 0.8 < report.scale < 1.0  # anny's legs are shorter than this 1.08x person's
    fe = floor_errors(src, out, report)
    assert np.all(fe.source_height < 1e-6)  # the source stands on its floor in every frame
    # anny's lowest foot joint stays on anny's floor: within 1.5 cm on average, 3 cm at worst (proportions differ)
    assert fe.height_error.mean() < 0.015 and fe.height_error.max() < 0.03
    assert fe.root_error.max() < 1e-6  # hip centre follows the source's, scaled by leg length
    # not vacuous: the walk moves 1.2 m/s and the feet do leave the floor in the source's swing phase
    assert np.ptp(out.root_position[:, 1]) > 1.0


def test_generic_t_pose_without_a_model_file_matches_smpl_conventions():
    """Without a model file: legs straight down, arms straight out, feet forward (SMPL's T-pose directions)."""
    sk = rig_motion.skeleton_of("smpl")
    r = dict(zip(sk.joint_names, sk.rest))
    down = r["left_ankle"] - r["left_hip"]
    out = r["left_wrist"] - r["left_shoulder"]
    fwd = r["left_foot"] - r["left_ankle"]
    assert np.degrees(np.arccos(-down[1] / np.linalg.norm(down))) < 5
    assert np.degrees(np.arccos(out[0] / np.linalg.norm(out))) < 2
    assert fwd[2] > 0.1
    assert "generic" in sk.source_note


def test_smplx_hands_and_face_on_smpl_are_dropped_with_a_note():
    F = 3
    rng = np.random.default_rng(0)
    m = BodyMotion(body_model="smplx", frame_index=np.arange(F), global_orient=rng.normal(0, .2, (F, 3)),
                   body_pose=rng.normal(0, .2, (F, 63)), transl=np.zeros((F, 3)),
                   left_hand_pose=rng.normal(0, .2, (F, 45)), right_hand_pose=rng.normal(0, .2, (F, 45)),
                   jaw_pose=rng.normal(0, .2, (F, 3)))
    src = rig_motion.to_skeleton_motion(m, rig_motion.skeleton_of("smplx"))
    out, report = retarget(src, rig_motion.skeleton_of("smpl"))
    assert len(report.dropped) == 3 + 28  # jaw, eyes, 28 of 30 finger joints (the middle bases -> palms)
    assert "jaw" in report.dropped and any("dropped" in n for n in report.notes)
    match = match_joints(src.skeleton, out.skeleton)
    t_names = {out.skeleton.joint_names[t]: src.skeleton.joint_names[s] for t, s in match.pairs}
    assert t_names["left_hand"] == "left_middle1"  # SMPL's palm takes the middle finger's base
    bm = rig_motion.to_body_motion(out, "smpl")
    assert bm.body_pose.shape == (F, 69)
    # the body part is the same rig: the 21 body joints keep their rotations (rest directions agree)
    ang = rotation_angle(np.swapaxes(out.local[:, 1:22], -1, -2) @ src.local[:, 1:22])
    assert ang.max() < 1e-6


def test_rotations_survive_a_y_up_world():
    """The same motion described in a y-up world retargets to the same result (world up handled)."""
    m = _random_smpl_motion(frames=4, seed=5)
    sk = rig_motion.skeleton_of("smpl")
    z_up = rig_motion.to_skeleton_motion(m, sk, world_up="z")
    W = np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])  # z-up world -> y-up world
    local = z_up.local.copy()
    local[:, 0] = W @ local[:, 0]
    y_up = SkeletonMotion(skeleton=sk, local=local, root_position=z_up.root_position @ W.T, fps=30.0, world_up="y")
    a, _ = retarget(z_up, rig_motion.skeleton_of("smplx"))
    b, _ = retarget(y_up, rig_motion.skeleton_of("smplx"))
    assert np.abs(a.local - b.local).max() < 1e-9 and np.abs(a.root_position - b.root_position).max() < 1e-9


@pytest.mark.anny
def test_smpl_to_anny_and_back_recovers_the_rotations(anny_skeleton):
    """Both directions agree: SMPL -> anny -> SMPL gives SMPL's own local rotations back (generic table)."""
    m = _random_smpl_motion(frames=5, seed=9)
    src = rig_motion.to_skeleton_motion(m, rig_motion.skeleton_of("smpl"))
    on_anny, _ = retarget(src, anny_skeleton)
    back, report = retarget(on_anny, rig_motion.skeleton_of("smpl"))
    assert len(report.mapped) == 24  # anny's middle-finger base stands for SMPL's palm joint (left_hand)
    assert len(report.dropped) == 28 + 2  # anny's other finger joints and its eyes: SMPL has none
    err = rotation_angle(np.swapaxes(src.local, -1, -2) @ back.local)  # [frames, 24] radians
    assert err.max() < 1e-6
    assert report.scale == pytest.approx(1.0 / retarget(src, anny_skeleton)[1].scale)
