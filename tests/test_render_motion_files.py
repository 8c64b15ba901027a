"""`--poses` motion files: anny npz (synth layout), AMASS SMPL+H / SMPL-X npz, and the body-model mismatch error."""

from __future__ import annotations

import numpy as np
import pytest

from avatarctl.body.motion import BodyMotion
from avatarctl.errors import InputError
from avatarctl.io.motion_files import adopt_subject, read_motion_file, root_translation, shift_motion


def _anny_npz(path, frames=5, with_labels=False):
    pose = np.broadcast_to(np.eye(4, dtype=np.float32), (frames, 104, 4, 4)).copy()
    pose[:, 0, 0, 3] = np.linspace(0, 0.4, frames)
    arrays = dict(body_model=np.array("anny"), pose_parameters=pose, phenotype=np.array([0.3, 0.7], np.float32),
                  phenotype_labels=np.array(["gender", "age"]), frame_index=np.arange(10, 10 + frames),
                  fps=np.array(25.0))
    if with_labels:
        arrays["bone_labels"] = np.array([f"b{i}" for i in range(104)])
    np.savez(path, **arrays)
    return path


def _amass_smplh(path, frames=6, key_rate="mocap_framerate"):
    rng = np.random.default_rng(0)
    np.savez(path, poses=rng.normal(0, 0.2, (frames, 156)).astype(np.float64),
             trans=rng.normal(0, 1, (frames, 3)), betas=rng.normal(0, 1, 16), gender=np.array("neutral"),
             dmpls=np.zeros((frames, 8)), **{key_rate: np.array(120.0)})
    return path


def _amass_smplx(path, frames=4, packed=True):
    rng = np.random.default_rng(1)
    poses = rng.normal(0, 0.2, (frames, 165))
    arrays = dict(trans=rng.normal(0, 1, (frames, 3)), betas=rng.normal(0, 1, 16), mocap_frame_rate=np.array(60.0),
                  gender=np.array("female"), surface_model_type=np.array("smplx"))
    if packed:
        arrays["poses"] = poses
    else:
        arrays.update(root_orient=poses[:, :3], pose_body=poses[:, 3:66], pose_jaw=poses[:, 66:69],
                      pose_eye=poses[:, 69:75], pose_hand=poses[:, 75:165])
    np.savez(path, **arrays)
    return path, poses


def test_anny_motion_file_as_written_by_synth(tmp_path):
    m = read_motion_file(_anny_npz(tmp_path / "motion.npz", with_labels=True), "anny")
    assert m.body_model == "anny" and m.num_frames == 5 and m.fps == 25.0
    assert list(m.frame_index) == [10, 11, 12, 13, 14]
    assert m.pose_parameters.shape == (5, 104, 4, 4)
    assert m.phenotype_labels == ("gender", "age")
    # a BodyMotion.save file reads back the same
    m.save(tmp_path / "body.npz")
    m2 = read_motion_file(tmp_path / "body.npz", "anny")
    assert np.array_equal(m2.pose_parameters, m.pose_parameters) and list(m2.frame_index) == list(m.frame_index)


def test_amass_smplh_to_smpl(tmp_path):
    p = _amass_smplh(tmp_path / "walk_poses.npz")
    raw = np.load(p)
    m = read_motion_file(p, "smpl")
    assert m.body_model == "smpl" and m.num_frames == 6 and m.fps == 120.0
    assert np.allclose(m.global_orient, raw["poses"][:, :3], atol=1e-6)
    assert m.body_pose.shape == (6, 69)
    assert np.allclose(m.body_pose[:, :63], raw["poses"][:, 3:66], atol=1e-6)
    assert np.all(m.body_pose[:, 63:] == 0)  # SMPL's hand joints: identity
    assert np.allclose(m.transl, raw["trans"], atol=1e-6) and m.betas.shape == (16,)


@pytest.mark.parametrize("packed", [True, False])
def test_amass_smplx_packed_and_separate_keys(tmp_path, packed):
    p, poses = _amass_smplx(tmp_path / "x.npz", packed=packed)
    m = read_motion_file(p, "smplx")
    assert m.body_model == "smplx" and m.fps == 60.0 and m.num_frames == 4
    assert np.allclose(m.global_orient, poses[:, :3], atol=1e-6)
    assert np.allclose(m.body_pose, poses[:, 3:66], atol=1e-6)
    assert np.allclose(m.jaw_pose, poses[:, 66:69], atol=1e-6)
    assert np.allclose(m.leye_pose, poses[:, 69:72], atol=1e-6) and np.allclose(m.reye_pose, poses[:, 72:75], atol=1e-6)
    assert np.allclose(m.left_hand_pose, poses[:, 75:120], atol=1e-6)
    assert np.allclose(m.right_hand_pose, poses[:, 120:165], atol=1e-6)


@pytest.mark.parametrize("maker,avatar,says", [
    ("amass_smplh", "anny", "SMPL+H"),
    ("amass_smplx", "smpl", "SMPL-X"),
    ("anny", "smpl", "anny"),
    ("anny", "smplx", "anny"),
    ("amass_smplh", "smplx", "SMPL+H"),
])
def test_body_model_mismatch_is_a_one_line_input_error(tmp_path, maker, avatar, says):
    path = tmp_path / "m.npz"
    if maker == "anny":
        _anny_npz(path)
    elif maker == "amass_smplh":
        _amass_smplh(path)
    else:
        _amass_smplx(path)
    with pytest.raises(InputError) as e:
        read_motion_file(path, avatar)
    msg = e.value.one_line()
    assert says in msg and f"avatar uses {avatar}" in msg and "->" in msg and "\n" not in msg


def test_bad_files_are_input_errors(tmp_path):
    with pytest.raises(InputError, match="not found"):
        read_motion_file(tmp_path / "missing.npz", "anny")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(InputError, match="cannot read"):
        read_motion_file(tmp_path / "junk.npz", "anny")
    np.savez(tmp_path / "nokeys.npz", foo=np.zeros(3))
    with pytest.raises(InputError, match="unrecognised"):
        read_motion_file(tmp_path / "nokeys.npz", "smpl")
    np.savez(tmp_path / "badwidth.npz", poses=np.zeros((3, 100)), trans=np.zeros((3, 3)))
    with pytest.raises(InputError, match="72 | 156 | 165"):
        read_motion_file(tmp_path / "badwidth.npz", "smpl")
    np.savez(tmp_path / "badtrans.npz", poses=np.zeros((3, 156)), trans=np.zeros((3, 2)), mocap_framerate=30.0)
    with pytest.raises(InputError, match="trans"):
        read_motion_file(tmp_path / "badtrans.npz", "smpl")
    np.savez(tmp_path / "obj.npz", poses=np.array([object()], dtype=object))
    with pytest.raises(InputError, match="pickle"):
        read_motion_file(tmp_path / "obj.npz", "smpl")
    pose = np.full((2, 104, 4, 4), np.nan, np.float32)
    np.savez(tmp_path / "nan.npz", body_model=np.array("anny"), pose_parameters=pose)
    with pytest.raises(InputError, match="non-finite"):
        read_motion_file(tmp_path / "nan.npz", "anny")


def test_adopt_subject_and_shift(tmp_path):
    m = read_motion_file(_anny_npz(tmp_path / "a.npz"), "anny")
    subject = BodyMotion(body_model="anny", frame_index=np.arange(1),
                         pose_parameters=np.eye(4)[None, None].repeat(104, 1),
                         phenotype=np.array([0.9], np.float32), phenotype_labels=("muscle",))
    a = adopt_subject(m, subject)
    assert a.phenotype_labels == ("muscle",) and np.allclose(a.phenotype, [0.9])
    assert np.array_equal(a.pose_parameters, m.pose_parameters)
    s = shift_motion(a, np.array([1.0, -2.0, 0.5]))
    assert np.allclose(root_translation(s) - root_translation(a), [1.0, -2.0, 0.5], atol=1e-6)
    smpl = read_motion_file(_amass_smplh(tmp_path / "s.npz"), "smpl")
    with pytest.raises(InputError, match="avatar is anny"):
        adopt_subject(smpl, subject)
