"""Motion formats for retargeting: the BVH reader / writer (`avatarctl.io.bvh`), AIST++ pickles read with the
restricted unpickler, `avatarctl motion` (the CLI over `stages.motion`) and its one-line errors on bad files."""

from __future__ import annotations

import json
import pickle

import numpy as np
import pytest
from typer.testing import CliRunner

from avatarctl.body.skeleton import rotation_angle
from avatarctl.cli.app import app
from avatarctl.errors import InputError
from avatarctl.io.bvh import read_bvh
from avatarctl.io.motion_files import read_motion
from fixtures.smpl import smpl_walk, write_amass_npz

BVH = """HIERARCHY
ROOT Hips
{
  OFFSET 0 90 0
  CHANNELS 6 Xposition Yposition Zposition Xrotation Yrotation Zrotation
  JOINT LeftUpLeg
  {
    OFFSET 10 -5 0
    CHANNELS 3 Zrotation Xrotation Yrotation
    JOINT LeftLeg
    {
      OFFSET 0 -40 0
      CHANNELS 3 Zrotation Xrotation Yrotation
      End Site
      {
        OFFSET 0 -40 0
      }
    }
  }
}
MOTION
Frames: 2
Frame Time: 0.04
1 90 2 10 20 30 0 0 0 -45 0 0
3 91 4 0 0 0 5 10 15 0 0 0
"""


def _rx(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _ry(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rz(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def test_bvh_reader_channel_orders_offsets_and_names(tmp_path):
    p = tmp_path / "a.bvh"
    p.write_text(BVH)
    m = read_bvh(p).motion
    sk = m.skeleton
    assert sk.joint_names == ("Hips", "LeftUpLeg", "LeftLeg") and sk.parents == (-1, 0, 1)
    assert sk.canonical == ("pelvis", "left_hip", "left_knee")  # the built-in Mixamo-style names
    assert m.fps == pytest.approx(25.0) and m.num_frames == 2
    assert np.allclose(sk.rest, [[0, 90, 0], [10, 85, 0], [10, 45, 0]])
    assert np.allclose(m.root_position, [[1, 90, 2], [3, 91, 4]])  # position channels are absolute
    d = np.radians
    assert np.allclose(m.local[0, 0], _rx(d(10)) @ _ry(d(20)) @ _rz(d(30)))  # rotations in the listed order
    assert np.allclose(m.local[1, 1], _rz(d(5)) @ _rx(d(10)) @ _ry(d(15)))
    assert np.allclose(m.local[0, 2], _rz(d(-45)))
    # forward kinematics: the knee hangs off the hip, rotated by the hip's world rotation
    P = m.joint_positions()
    assert np.allclose(P[0, 1], m.root_position[0] + m.local[0, 0] @ np.array([10, -5, 0]))


@pytest.mark.anny
def test_anny_motion_bvh_round_trip_keeps_rotations(tmp_path):
    """anny motion -> BVH -> anny: the same joint rotations to 1e-4 rad (every one of the 104 bones moves)."""
    from avatarctl.body.skeleton import axis_angle_to_matrix
    from avatarctl.stages.motion import MotionConfig, run

    rng = np.random.default_rng(0)
    F = 5
    pose = np.broadcast_to(np.eye(4, dtype=np.float32), (F, 104, 4, 4)).copy()
    pose[:, :, :3, :3] = axis_angle_to_matrix(rng.normal(0, 0.5, (F, 104, 3)))
    pose[:, 0, :3, 3] = rng.normal(0, 0.5, (F, 3))
    src = tmp_path / "anny.npz"
    np.savez(src, body_model=np.array("anny"), pose_parameters=pose, fps=np.array(24.0))
    run(MotionConfig(source=str(src), to="anny", out=str(tmp_path / "anny.bvh")))
    text = (tmp_path / "anny.bvh").read_text()
    assert text.count("JOINT ") == 103 and "Frames: 5" in text
    res = run(MotionConfig(source=str(tmp_path / "anny.bvh"), to="anny", out=str(tmp_path / "back.npz")))
    assert res.retargeted and res.mapped == 104 and any("same rig" in n for n in res.notes)
    back = np.load(tmp_path / "back.npz")
    R0, R1 = pose[:, :, :3, :3].astype(np.float64), back["pose_parameters"][:, :, :3, :3].astype(np.float64)
    err = rotation_angle(np.swapaxes(R0, -1, -2) @ R1)  # [frames, 104] radians
    assert err.max() < 1e-4
    assert np.abs(back["pose_parameters"][:, 0, :3, 3] - pose[:, 0, :3, 3]).max() < 1e-5  # metres
    assert float(back["fps"]) == pytest.approx(24.0)


def _aist_pkl(path, frames=4, **over):
    rng = np.random.default_rng(0)
    data = {"smpl_poses": rng.normal(0, 0.2, (frames, 72)), "smpl_trans": rng.normal(0, 50, (frames, 3)),
            "smpl_scaling": np.array([93.0]), "smpl_loss": 1.5}
    data.update(over)
    with open(path, "wb") as fh:
        pickle.dump(data, fh)
    return data


def test_aist_pickle_reads_with_the_restricted_unpickler(tmp_path):
    data = _aist_pkl(tmp_path / "gBR.pkl")
    inp = read_motion(tmp_path / "gBR.pkl")
    assert inp.kind == "aist" and inp.world_up == "y" and inp.fps == 60.0
    assert np.allclose(inp.body.transl, data["smpl_trans"] / 93.0, atol=1e-5)
    assert np.allclose(inp.body.body_pose, data["smpl_poses"][:, 3:], atol=1e-6)

    class Evil:
        def __reduce__(self):
            import os

            return (os.system, ("echo pwned",))

    with open(tmp_path / "evil.pkl", "wb") as fh:
        pickle.dump({"smpl_poses": Evil()}, fh)
    with pytest.raises(InputError, match="is not allowed in a data file"):
        read_motion(tmp_path / "evil.pkl")


def _cli(*args):
    return CliRunner().invoke(app, ["motion", *map(str, args)])


def _assert_one_line_error(res, *needles):
    assert res.exit_code == 2, res.output
    assert "Traceback" not in res.output and (res.exception is None or isinstance(res.exception, SystemExit))
    line = " ".join(res.output.split())  # rich wraps long lines
    assert line.startswith("error:") and "->" in line, res.output
    for n in needles:
        assert n in line, res.output


def test_motion_cli_bad_files_are_one_line_errors(tmp_path):
    out = tmp_path / "out.npz"
    # unknown skeleton: a BVH whose joints have no known names
    (tmp_path / "odd.bvh").write_text(BVH.replace("Hips", "Bone0").replace("LeftUpLeg", "Bone1")
                                      .replace("LeftLeg", "Bone2"))
    _assert_one_line_error(_cli(tmp_path / "odd.bvh", "--to", "anny", "-o", out), "cannot retarget", "0 of 3",
                           "--name-map", "odd.bvh")
    # missing keys
    _aist_pkl(tmp_path / "nokeys.pkl")
    data = pickle.loads((tmp_path / "nokeys.pkl").read_bytes())
    del data["smpl_trans"]
    (tmp_path / "nokeys.pkl").write_bytes(pickle.dumps(data))
    _assert_one_line_error(_cli(tmp_path / "nokeys.pkl", "--to", "smpl", "-o", out), "lacks smpl_trans",
                           "nokeys.pkl")
    # a misspelt frame-rate key
    poses, trans = smpl_walk(5)
    np.savez(tmp_path / "rate.npz", poses=poses, trans=trans, mocap_frame_rte=np.array(60.0))
    _assert_one_line_error(_cli(tmp_path / "rate.npz", "--to", "smpl", "-o", out), "mocap_frame_rte",
                           "mocap_framerate", "rate.npz")
    # NaN
    poses[2, 5] = np.nan
    write_amass_npz(tmp_path / "nan.npz", poses, trans)
    _assert_one_line_error(_cli(tmp_path / "nan.npz", "--to", "anny", "-o", out), "non-finite", "nan.npz")
    # a truncated BVH names the line
    (tmp_path / "cut.bvh").write_text(BVH[:BVH.index("MOTION")])
    _assert_one_line_error(_cli(tmp_path / "cut.bvh", "--to", "smpl", "-o", out), "malformed BVH", "cut.bvh:")
    # a bad name map
    (tmp_path / "map.json").write_text(json.dumps({"Bone0": "hips"}))
    _assert_one_line_error(_cli(tmp_path / "odd.bvh", "--name-map", tmp_path / "map.json", "-o", out),
                           "unknown joints: hips")
    assert not out.exists()


def test_motion_cli_bvh_with_a_name_map_to_smpl(tmp_path):
    (tmp_path / "odd.bvh").write_text(BVH.replace("Hips", "Bone0").replace("LeftUpLeg", "Bone1")
                                      .replace("LeftLeg", "Bone2"))
    # a one-legged skeleton: the map names its joints, the right leg is simply absent
    (tmp_path / "map.json").write_text(json.dumps({"Bone0": "pelvis", "Bone1": "left_hip", "Bone2": "left_knee"}))
    res = _cli(tmp_path / "odd.bvh", "--name-map", tmp_path / "map.json", "--to", "smpl", "-o", tmp_path / "o.npz")
    # no ankle: the leg length cannot be measured -> a one-line error that says what is missing
    _assert_one_line_error(res, "no mapped legs")


def test_motion_amass_to_smplx_and_bvh(tmp_path):
    from avatarctl.stages.motion import MotionConfig, run

    poses, trans = smpl_walk(12)
    write_amass_npz(tmp_path / "walk.npz", poses, trans, fps=60.0)
    res = _cli(tmp_path / "walk.npz", "--to", "smplx", "-o", tmp_path / "walk_x.npz")
    assert res.exit_code == 0, res.output
    assert "mapped" in res.output and "feet vs floor" in res.output
    r = run(MotionConfig(source=str(tmp_path / "walk.npz"), to="smplx", out=str(tmp_path / "walk_x.npz")))
    # SMPL+H's 52 joints (fingers included) all reach SMPL-X; SMPL-X's jaw and eyes get no source
    assert r.retargeted and r.mapped == 52 and r.dropped == () and r.frames == 12 and r.fps == 60.0
    assert "retargeted smplh" in r.summary and r.floor_error_cm is not None and r.floor_error_cm[1] < 1e-3
    inp = read_motion(tmp_path / "walk_x.npz")
    assert inp.kind == "smplx" and inp.num_frames == 12 and inp.fps == 60.0
    with np.load(tmp_path / "walk_x.npz") as z:  # the output says where it came from
        prov = json.loads(str(z["provenance"]))
    assert prov["to"] == "smplx" and prov["source_kind"] == "smplh" and ["left_hip", "left_hip"] in prov["mapped"]
    # made for SMPL already: used as is (the fingers dropped), written as a 24-joint BVH
    r = run(MotionConfig(source=str(tmp_path / "walk.npz"), to="smpl", out=str(tmp_path / "walk_s.bvh")))
    assert not r.retargeted and "used as is" in r.summary and any("finger" in n for n in r.notes)
    back = read_motion(tmp_path / "walk_s.bvh")
    assert back.kind == "bvh" and back.skeleton.skeleton.num_joints == 24


def test_a_mixamo_named_bvh_retargets_like_the_smpl_motion_it_came_from(tmp_path):
    """An SMPL walk written as BVH with Mixamo joint names (cm, y up) and read back retargets onto SMPL-X exactly as
    the SMPL motion does: the BVH path (reader, built-in names, units, axes) adds nothing."""
    from dataclasses import replace

    from avatarctl.body import rig_motion
    from avatarctl.body.motion import BodyMotion
    from avatarctl.body.retarget import retarget
    from avatarctl.io.bvh import write_bvh

    poses, trans = smpl_walk(10)
    m = BodyMotion(body_model="smpl", frame_index=np.arange(10), global_orient=poses[:, :3], body_pose=poses[:, 3:],
                   transl=trans)
    sm = rig_motion.to_skeleton_motion(m, rig_motion.skeleton_of("smpl"))
    mixamo = {"pelvis": "mixamorig:Hips", "spine1": "Spine", "spine2": "Spine1", "spine3": "Spine2", "neck": "Neck",
              "head": "Head", "left_hand": "LeftPalm", "right_hand": "RightPalm"}
    for s, B in (("left", "Left"), ("right", "Right")):
        mixamo.update({f"{s}_hip": f"{B}UpLeg", f"{s}_knee": f"{B}Leg", f"{s}_ankle": f"{B}Foot",
                       f"{s}_foot": f"{B}ToeBase", f"{s}_collar": f"{B}Shoulder", f"{s}_shoulder": f"{B}Arm",
                       f"{s}_elbow": f"{B}ForeArm", f"{s}_wrist": f"{B}Hand"})
    names = tuple(mixamo[n] for n in sm.skeleton.joint_names)
    write_bvh(tmp_path / "walk.bvh", replace(sm, skeleton=replace(sm.skeleton, joint_names=names)))
    bvh = read_motion(tmp_path / "walk.bvh").skeleton
    assert sum(c is not None for c in bvh.skeleton.canonical) == 22  # the palms have no Mixamo name
    target = rig_motion.skeleton_of("smplx")
    a, _ = retarget(sm, target)
    b, rep = retarget(bvh, target)
    assert rep.scale == pytest.approx(0.01, rel=1e-6)  # centimetres in the file
    body = slice(0, 22)  # the palms' rotation reaches SMPL-X's middle fingers only in `a`
    assert np.abs(a.local[:, body] - b.local[:, body]).max() < 1e-6
    assert np.abs(a.root_position - b.root_position).max() < 1e-6


def test_retargeting_onto_the_toy_body_is_refused(tmp_path):
    from avatarctl.io.motion_convert import convert_motion

    poses, trans = smpl_walk(3)
    inp = read_motion(write_amass_npz(tmp_path / "walk.npz", poses, trans))
    with pytest.raises(InputError, match="cannot retarget motion onto the 'toy' body model"):
        convert_motion(inp, "toy")


def test_bvh_writer_euler_angles_recompose_even_at_gimbal_lock():
    from avatarctl.body.skeleton import axis_angle_to_matrix
    from avatarctl.io.bvh import _axis_rotation, _zyx_degrees

    def compose(deg):  # Zrotation Yrotation Xrotation, as the writer declares its channels
        return _axis_rotation(2, deg[..., 0]) @ _axis_rotation(1, deg[..., 1]) @ _axis_rotation(0, deg[..., 2])

    R = axis_angle_to_matrix(np.random.default_rng(0).normal(0, 2, (500, 3)))
    R = np.concatenate([R, compose(np.array([[30.0, 90.0, 20.0], [10.0, -90.0, 45.0]]))])  # y = +-90 deg
    err = rotation_angle(np.swapaxes(R, -1, -2) @ compose(_zyx_degrees(R)))
    assert err.max() < 1e-9
