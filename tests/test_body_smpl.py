"""SMPL / SMPL-X from a user file (`avatarctl/body/smpl.py`), checked against the `smplx` package.

Model files are RANDOM arrays in the official formats (tests/fixtures/smpl.py), never real SMPL files.
SMPL-X hand convention under test: hand poses are full axis-angle relative to the flat hand
(smplx `use_pca=False, flat_hand_mean=True`); `add_hand_mean=True` matches smplx `flat_hand_mean=False`.
"""

from __future__ import annotations

import pickle
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from avatarctl.body.lbs import axis_angle_to_matrix, inverse_lbs, lbs, transform_points
from avatarctl.body.motion import BodyMotion
from avatarctl.body.registry import load_body_model
from avatarctl.body.smpl import SMPL_JOINT_NAMES, SMPLX_JOINT_NAMES, SmplBody
from avatarctl.errors import InputError

sys.path.insert(0, str(Path(__file__).parent))
from fixtures.smpl import (SMPL_PARENTS, SMPLX_PARENTS, random_smpl_arrays, write_random_smpl_npz,  # noqa: E402
                           write_random_smpl_pkl)

smplx = pytest.importorskip("smplx")

FRAMES = 4
TOL = 1e-5  # metres: the bar of the brief, vs smplx in float32


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("models")
    out = {
        "smpl_pkl": write_random_smpl_pkl(d / "SMPL_NEUTRAL.pkl", "smpl", seed=0),
        "smpl_plain_pkl": write_random_smpl_pkl(d / "SMPL_plain.pkl", "smpl", seed=0, chumpy=False),
        "smpl_npz": write_random_smpl_npz(d / "SMPL_NEUTRAL.npz", "smpl", seed=0),
        "smplx_pkl": write_random_smpl_pkl(d / "SMPLX_NEUTRAL.pkl", "smplx", seed=1),
        "smplx_npz": write_random_smpl_npz(d / "SMPLX_NEUTRAL.npz", "smplx", seed=1),
    }
    assert "chumpy" not in sys.modules and "chumpy.ch" not in sys.modules
    return out


@pytest.fixture(scope="module")
def smpl_body(files) -> SmplBody:
    return SmplBody.from_file(files["smpl_pkl"], kind="smpl")


@pytest.fixture(scope="module")
def smplx_body(files) -> SmplBody:
    return SmplBody.from_file(files["smplx_pkl"], kind="smplx")


def random_motion(kind: str, seed: int = 0, frames: int = FRAMES, num_betas: int = 10,
                  num_expression: int = 10) -> BodyMotion:
    rng = np.random.default_rng(seed)
    kw = dict(global_orient=rng.normal(0, 1.2, (frames, 3)), transl=rng.normal(0, 1.0, (frames, 3)),
              body_pose=rng.normal(0, 0.5, (frames, 69 if kind == "smpl" else 63)),
              betas=rng.normal(0, 1.0, num_betas))
    if kind == "smplx":
        kw.update(jaw_pose=rng.normal(0, 0.3, (frames, 3)), leye_pose=rng.normal(0, 0.3, (frames, 3)),
                  reye_pose=rng.normal(0, 0.3, (frames, 3)), left_hand_pose=rng.normal(0, 0.5, (frames, 45)),
                  right_hand_pose=rng.normal(0, 0.5, (frames, 45)),
                  expression=rng.normal(0, 1.0, (frames, num_expression)))
    return BodyMotion(body_model=kind, frame_index=np.arange(frames), **kw)


def smplx_reference(kind: str, path: Path, motion: BodyMotion, dtype: torch.dtype, num_betas: int = 10,
                    num_expression: int = 10, flat_hand_mean: bool = True):
    """Run the smplx package on `motion`; returns (vertices [F, V, 3], joints [F, J, 3]) as float64."""
    F = motion.num_frames
    if kind == "smpl":
        model = smplx.SMPL(model_path=str(path), num_betas=num_betas, dtype=dtype, batch_size=F)
        names = ("global_orient", "body_pose", "transl")
    else:
        model = smplx.SMPLX(model_path=str(path), ext="npz", num_betas=num_betas,
                            num_expression_coeffs=num_expression, use_pca=False, flat_hand_mean=flat_hand_mean,
                            dtype=dtype, batch_size=F)
        names = ("global_orient", "body_pose", "transl", "jaw_pose", "leye_pose", "reye_pose", "left_hand_pose",
                 "right_hand_pose", "expression")
    kw = {n: torch.as_tensor(getattr(motion, n), dtype=dtype) for n in names}
    kw["betas"] = torch.as_tensor(motion.betas, dtype=dtype)[None].expand(F, -1)
    with torch.no_grad():
        out = model(**kw)
    J = 24 if kind == "smpl" else 55
    return out.vertices.double(), out.joints[:, :J].double()


# ---- reading files ------------------------------------------------------------------------------------------
def test_chumpy_pickle_loads_without_chumpy(files):
    # the file really references chumpy: a plain unpickle fails without it
    with open(files["smpl_pkl"], "rb") as fh, pytest.raises(ModuleNotFoundError, match="chumpy"):
        pickle.load(fh, encoding="latin1")
    body = SmplBody.from_file(files["smpl_pkl"], kind="smpl")
    assert "chumpy" not in sys.modules
    ref = random_smpl_arrays("smpl", seed=0)
    np.testing.assert_array_equal(body.data.v_template, ref["v_template"])
    np.testing.assert_array_equal(body.data.j_regressor, ref["J_regressor"].toarray())
    np.testing.assert_array_equal(body.data.posedirs, ref["posedirs"].astype(np.float64))
    assert body.parents == SMPL_PARENTS and body.joint_names == SMPL_JOINT_NAMES
    assert body.num_vertices == 6890 and body.num_betas == 10 and body.num_expression == 0


def test_pkl_plain_and_npz_agree(files, smpl_body):
    motion = random_motion("smpl", seed=3)
    ref = smpl_body.pose(motion).vertices
    for key in ("smpl_plain_pkl", "smpl_npz"):
        other = SmplBody.from_file(files[key], kind="smpl").pose(motion).vertices
        assert torch.equal(other, ref), key


# ---- against smplx ------------------------------------------------------------------------------------------
def test_smpl_matches_smplx(files, smpl_body):
    motion = random_motion("smpl", seed=4)
    posed = smpl_body.pose(motion)
    joints = smpl_body.joints(motion)
    v32, j32 = smplx_reference("smpl", files["smpl_plain_pkl"], motion, torch.float32)
    v64, j64 = smplx_reference("smpl", files["smpl_plain_pkl"], motion, torch.float64)
    assert (posed.vertices.double() - v32).abs().max() <= TOL
    assert (joints.double() - j32).abs().max() <= TOL
    ev = smpl_body.evaluate(motion)  # float64 internals vs float64 smplx
    # smplx's Rodrigues adds 1e-8 to the axis-angle, hence ~5e-8 m and not machine precision
    assert (ev.vertices - v64).abs().max() <= 2e-7
    assert (ev.joints - j64).abs().max() <= 2e-7


def test_smplx_matches_smplx(files, smplx_body):
    motion = random_motion("smplx", seed=5)
    posed = smplx_body.pose(motion)
    joints = smplx_body.joints(motion)
    v32, j32 = smplx_reference("smplx", files["smplx_npz"], motion, torch.float32)
    v64, j64 = smplx_reference("smplx", files["smplx_npz"], motion, torch.float64)
    assert posed.vertices.shape == (FRAMES, 10475, 3) and joints.shape == (FRAMES, 55, 3)
    assert (posed.vertices.double() - v32).abs().max() <= TOL
    assert (joints.double() - j32).abs().max() <= TOL
    ev = smplx_body.evaluate(motion)
    # smplx's Rodrigues adds 1e-8 to the axis-angle, hence ~5e-8 m and not machine precision
    assert (ev.vertices - v64).abs().max() <= 2e-7
    assert (ev.joints - j64).abs().max() <= 2e-7
    # every part of the pose matters (a dropped jaw / eye / hand / expression would go unnoticed otherwise)
    for name in ("jaw_pose", "leye_pose", "left_hand_pose", "right_hand_pose", "expression"):
        changed = replace(motion, **{name: np.zeros_like(getattr(motion, name))})
        assert (smplx_body.pose(changed).vertices - posed.vertices).abs().max() > 1e-4, name


def test_smplx_hand_mean_convention(files, smplx_body):
    motion = random_motion("smplx", seed=6, frames=2)
    with_mean = SmplBody(smplx_body.data, add_hand_mean=True)
    v32, _ = smplx_reference("smplx", files["smplx_npz"], motion, torch.float32, flat_hand_mean=False)
    assert (with_mean.pose(motion).vertices.double() - v32).abs().max() <= TOL
    assert (smplx_body.pose(motion).vertices.double() - v32).abs().max() > 1e-3  # the conventions do differ


def test_smplx_300_betas_100_expression_layout(tmp_path):
    pkl = write_random_smpl_pkl(tmp_path / "m.pkl", "smplx", seed=2, num_betas=300, num_expression=100)
    npz = write_random_smpl_npz(tmp_path / "m.npz", "smplx", seed=2, num_betas=300, num_expression=100)
    body = SmplBody.from_file(pkl, kind="smplx")
    assert body.num_betas == 300 and body.num_expression == 100
    motion = random_motion("smplx", seed=7, frames=2, num_betas=300, num_expression=100)
    v32, j32 = smplx_reference("smplx", npz, motion, torch.float32, num_betas=300, num_expression=100)
    assert (body.pose(motion).vertices.double() - v32).abs().max() <= TOL
    assert (body.joints(motion).double() - j32).abs().max() <= TOL


# ---- the BodyModel contract -----------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["smpl", "smplx"])
def test_lbs_of_template_reproduces_posed_mesh(kind, smpl_body, smplx_body):
    body = smpl_body if kind == "smpl" else smplx_body
    motion = random_motion(kind, seed=8)
    tpl = body.template(motion)
    posed = body.pose(motion)
    J = 24 if kind == "smpl" else 55
    assert tpl.vertices.dtype == torch.float32 and posed.vertices.dtype == torch.float32
    assert posed.joint_transforms.shape == (FRAMES, J, 4, 4) and posed.pose_features.shape == (FRAMES, J, 3)
    assert tpl.parents == (SMPL_PARENTS if kind == "smpl" else SMPLX_PARENTS)
    assert tpl.joint_names == (SMPL_JOINT_NAMES if kind == "smpl" else SMPLX_JOINT_NAMES)
    assert torch.allclose(tpl.skin_weights.sum(1), torch.ones(tpl.vertices.shape[0]), atol=1e-6)
    # canonical = v_template + shapedirs . betas
    d = body.data
    expected = d.v_template + d.shapedirs @ motion.betas.astype(np.float64)
    assert np.abs(tpl.vertices.numpy() - expected).max() < 1e-6
    # Eq. 2 with the canonical-space blend offsets gives the posed mesh, including transl
    offsets = body.blend_offsets(motion)
    again = lbs(tpl.vertices[None] + offsets, tpl.skin_weights, posed.joint_transforms)
    assert (again - posed.vertices).abs().max() <= TOL
    # without the offsets LBS is off by at most their size (a blended rotation never lengthens a vector)
    plain = lbs(tpl.vertices, tpl.skin_weights, posed.joint_transforms)
    miss = (plain - posed.vertices).norm(dim=-1)  # [frames, V]
    assert miss.max() > 1e-4 and torch.all(miss <= offsets.norm(dim=-1) + TOL)
    # joints: M_j applied to the rest joint; the pelvis moves with transl
    ev = body.evaluate(motion)
    assert torch.allclose(transform_points(ev.joint_transforms, ev.rest_joints), ev.joints, atol=1e-10)
    # pose features: root zeroed, others the local rotation
    assert torch.all(posed.pose_features[:, 0] == 0)
    want = torch.as_tensor(motion.body_pose[:, :3], dtype=torch.float32)  # joint 1 (left hip)
    assert torch.allclose(posed.pose_features[:, 1], want, atol=1e-4)


def test_inverse_lbs_round_trip_smpl(smpl_body):
    motion = random_motion("smpl", seed=9)
    tpl = smpl_body.template(motion)
    M = smpl_body.pose(motion).joint_transforms.double()
    x = tpl.vertices.double()
    # weights renormalised in float64: inverse_lbs inverts the full 4x4 blend, whose corner is sum(w)
    w = tpl.skin_weights.double()
    w = w / w.sum(1, keepdim=True)
    back = inverse_lbs(lbs(x, w, M), w, M)
    err = (back - x).abs().max().item()
    assert err <= 1e-9, err  # float64; the blended rotations here have condition numbers < 3
    # float32 throughout: round trip within 1e-5 m
    back32 = inverse_lbs(lbs(tpl.vertices, tpl.skin_weights, M.float()), tpl.skin_weights, M.float())
    assert (back32 - tpl.vertices).abs().max() <= 1e-5


def test_chunking_and_frame_batching_agree(smplx_body):
    motion = random_motion("smplx", seed=10, frames=5)
    chunked = SmplBody(smplx_body.data, chunk=2)
    a = smplx_body.pose(motion)
    b = chunked.pose(motion)
    assert torch.equal(a.vertices, b.vertices) and torch.equal(a.joint_transforms, b.joint_transforms)
    single = smplx_body.pose(motion.select([3]))
    assert (single.vertices[0] - a.vertices[3]).abs().max() < 1e-6


def test_missing_optional_smplx_parts_default_to_zero(smplx_body):
    full = random_motion("smplx", seed=11, frames=2)
    minimal = BodyMotion(body_model="smplx", frame_index=full.frame_index, global_orient=full.global_orient,
                         body_pose=full.body_pose, transl=full.transl, betas=full.betas)
    zeros = {n: np.zeros_like(getattr(full, n)) for n in ("jaw_pose", "leye_pose", "reye_pose", "left_hand_pose",
                                                          "right_hand_pose", "expression")}
    explicit = BodyMotion(body_model="smplx", frame_index=full.frame_index, global_orient=full.global_orient,
                          body_pose=full.body_pose, transl=full.transl, betas=full.betas, **zeros)
    assert torch.equal(smplx_body.pose(minimal).vertices, smplx_body.pose(explicit).vertices)


# ---- joint transforms -> parameters (the refined fits of pose refinement, fit/refined.py) ---------------------
@pytest.mark.parametrize("kind,hand_mean", [("smpl", False), ("smplx", False), ("smplx", True)])
def test_parameters_from_joint_transforms_round_trip(kind, hand_mean, smpl_body, smplx_body):
    """pose -> transforms -> parameters -> transforms within 1e-5 (float32 parameters, as stored)."""
    body = smpl_body if kind == "smpl" else SmplBody(smplx_body.data, add_hand_mean=hand_mean)
    motion = random_motion(kind, seed=13)
    M = body.evaluate(motion, with_vertices=False).joint_transforms  # [F, J, 4, 4] float64
    back = body.motion_from_joint_transforms(motion, M)
    again = body.evaluate(back, with_vertices=False).joint_transforms
    assert (again - M).abs().max() <= 1e-5
    # the parameters themselves: same rotations (axis-angle may differ by 2 pi), same transl, the rest kept
    for name in ("global_orient", "body_pose") + (("jaw_pose", "left_hand_pose", "right_hand_pose") if kind == "smplx" else ()):
        a = torch.as_tensor(getattr(motion, name), dtype=torch.float64).reshape(FRAMES, -1, 3)
        b = torch.as_tensor(getattr(back, name), dtype=torch.float64).reshape(FRAMES, -1, 3)
        assert (axis_angle_to_matrix(a) - axis_angle_to_matrix(b)).abs().max() <= 1e-5, name
    assert np.abs(back.transl - motion.transl).max() <= 1e-5
    assert np.array_equal(back.betas, motion.betas) and np.array_equal(back.frame_index, motion.frame_index)
    if kind == "smplx":
        assert np.array_equal(back.expression, motion.expression)
    with pytest.raises(ValueError, match="joint_transforms must be"):
        body.motion_from_joint_transforms(motion, M[:, :10])


@pytest.mark.parametrize("kind", ["smpl", "smplx"])
def test_refined_fits_file_for_smpl(kind, smpl_body, smplx_body, tmp_path):
    """A fit's pose corrections (model/pose_refine.py, centres estimated as fit/loop.py does) come back as an
    SMPL / SMPL-X motion file whose transforms are the refined ones, and which differs from the input."""
    from avatarctl.body.joints import joint_centres, skin_weighted_centroids
    from avatarctl.fit.conditioning import build_pose_table
    from avatarctl.fit.refined import FILE_NAME, write_refined_fits
    from avatarctl.model.pose_refine import PoseRefinement

    body = smpl_body if kind == "smpl" else smplx_body
    motion = replace(random_motion(kind, seed=14, frames=6), frame_index=np.arange(10, 16))
    if kind == "smplx":  # random expression directions move every joint's rest position: no fixed centres
        motion = replace(motion, expression=np.zeros_like(motion.expression))
    frames = [11, 13, 14]
    poses = build_pose_table(body, motion, frames)
    tpl = body.template(motion)
    refine = PoseRefinement(num_frames=len(frames), parents=body.parents)
    refine.set_centres(joint_centres(poses.joint_transforms, body.parents,
                                     skin_weighted_centroids(tpl.vertices, tpl.skin_weights)))
    with torch.no_grad():
        refine.delta.normal_(0.0, 0.1, generator=torch.Generator().manual_seed(0))
        refine.tau.normal_(0.0, 0.02, generator=torch.Generator().manual_seed(1))
        want = refine(poses.joint_transforms.double(), torch.arange(len(frames)))
    summary = write_refined_fits(tmp_path, body, motion, poses, refine)
    assert summary.path == tmp_path / FILE_NAME
    got = BodyMotion.load(summary.path)
    assert got.body_model == kind and list(got.frame_index) == frames
    M = body.evaluate(got, with_vertices=False).joint_transforms
    # rotations exact; positions within the estimated centres' distance from the model's joints (sub-mm here)
    assert (M[..., :3, :3] - want[..., :3, :3]).abs().max() <= 1e-5
    assert (M[..., :3, 3] - want[..., :3, 3]).abs().max() <= 1e-3  # measured 0.3 / 0.4 mm (ridge pull)
    before = body.evaluate(motion.for_frames(frames), with_vertices=False).joint_transforms
    assert (before - want).abs().max() > 0.05  # the corrections were real


@pytest.mark.gpu
def test_cuda_matches_cpu(files):
    if not torch.cuda.is_available():
        pytest.skip("no CUDA device")
    motion = random_motion("smplx", seed=12)
    cpu = SmplBody.from_file(files["smplx_pkl"], kind="smplx").pose(motion)
    gpu = SmplBody.from_file(files["smplx_pkl"], kind="smplx", device="cuda").pose(motion)
    assert gpu.vertices.device.type == "cuda"
    assert (gpu.vertices.cpu() - cpu.vertices).abs().max() <= 1e-6


# ---- errors ---------------------------------------------------------------------------------------------------
def test_registry_needs_a_path(tmp_path, files):
    with pytest.raises(InputError, match="--body-model-path") as e:
        load_body_model("smpl")
    assert e.value.fix
    with pytest.raises(InputError, match="not found") as e:
        load_body_model("smplx", tmp_path / "nope.pkl")
    assert e.value.fix and "nope.pkl" in str(e.value)
    body = load_body_model("smpl", files["smpl_npz"])
    assert isinstance(body, SmplBody) and body.name == "smpl"


def test_wrong_kind_names_the_right_one(files):
    with pytest.raises(InputError, match="--body-model smplx"):
        SmplBody.from_file(files["smplx_npz"], kind="smpl")
    with pytest.raises(InputError, match="--body-model smpl"):
        SmplBody.from_file(files["smpl_npz"], kind="smplx")


def test_bad_files_are_one_line_input_errors(tmp_path, files):
    arrays = random_smpl_arrays("smpl", seed=0)
    # missing key
    partial = {k: np.asarray(v.toarray() if hasattr(v, "toarray") else v) for k, v in arrays.items()
               if k != "posedirs"}
    np.savez(tmp_path / "partial.npz", **partial)
    with pytest.raises(InputError, match="posedirs"):
        SmplBody.from_file(tmp_path / "partial.npz", kind="smpl")
    # truncated pickle
    (tmp_path / "cut.pkl").write_bytes(files["smpl_pkl"].read_bytes()[:5000])
    with pytest.raises(InputError, match="cannot read"):
        SmplBody.from_file(tmp_path / "cut.pkl", kind="smpl")
    # a pickle that would run code is refused, and nothing runs
    marker = tmp_path / "ran"

    class Evil:
        def __reduce__(self):
            return (Path.touch, (marker,))

    (tmp_path / "evil.pkl").write_bytes(pickle.dumps({"v_template": Evil()}, protocol=2))
    with pytest.raises(InputError, match="not allowed"):
        SmplBody.from_file(tmp_path / "evil.pkl", kind="smpl")
    assert not marker.exists()
    # wrong shapes
    bad = dict(partial, posedirs=np.zeros((6890, 3, 10)))
    np.savez(tmp_path / "bad.npz", **bad)
    with pytest.raises(InputError, match="posedirs") as e:
        SmplBody.from_file(tmp_path / "bad.npz", kind="smpl")
    assert "\n" not in str(e.value)


def test_motion_mismatches_are_input_errors(smpl_body):
    with pytest.raises(InputError, match="smplx"):
        smpl_body.pose(random_motion("smplx"))
    too_many = BodyMotion(body_model="smpl", frame_index=[0], global_orient=np.zeros((1, 3)),
                          body_pose=np.zeros((1, 69)), transl=np.zeros((1, 3)), betas=np.ones(16))
    with pytest.raises(InputError, match="16 non-zero betas"):
        smpl_body.pose(too_many)
    padded = BodyMotion(body_model="smpl", frame_index=[0], global_orient=np.zeros((1, 3)),
                        body_pose=np.zeros((1, 69)), transl=np.zeros((1, 3)), betas=np.r_[np.ones(3), np.zeros(13)])
    short = BodyMotion(body_model="smpl", frame_index=[0], global_orient=np.zeros((1, 3)),
                       body_pose=np.zeros((1, 69)), transl=np.zeros((1, 3)), betas=np.ones(3))
    assert torch.equal(smpl_body.pose(padded).vertices, smpl_body.pose(short).vertices)
