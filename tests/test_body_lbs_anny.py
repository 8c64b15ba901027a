"""`avatarctl/body/lbs.py` (rotations, forward kinematics, Eq. 1-2) and the anny wrapper (`anny_model.py`)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from avatarctl.body.lbs import (axis_angle_to_matrix, blend_transforms, forward_kinematics, inverse_lbs, lbs,
                                make_transform, matrix_to_axis_angle, rigid_inverse, transform_points)
from avatarctl.body.motion import BodyMotion

F64 = torch.float64


def rot_z(deg: float) -> torch.Tensor:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=F64)


def random_axes(n: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=F64), dim=-1)


# ---- rotations ------------------------------------------------------------------------------------------------
def test_rodrigues_hand_example():
    R = axis_angle_to_matrix(torch.tensor([0.0, 0.0, math.pi / 2], dtype=F64))
    assert torch.allclose(R, rot_z(90), atol=1e-15)
    R = axis_angle_to_matrix(torch.tensor([math.pi, 0.0, 0.0], dtype=F64))
    assert torch.allclose(R, torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=F64)), atol=1e-15)


@pytest.mark.parametrize("angle", [0.0, 1e-12, 1e-9, 1e-7, 1e-5, 1e-3, 0.5, math.pi / 2, 2.0, 3.0,
                                   math.pi - 1e-3, math.pi - 1e-5, math.pi - 1e-8, math.pi])
def test_axis_angle_matrix_round_trip(angle):
    aa = random_axes(200, seed=1) * angle
    R = axis_angle_to_matrix(aa)
    assert torch.allclose(R @ R.transpose(-1, -2), torch.eye(3, dtype=F64).expand_as(R), atol=1e-14)
    assert torch.allclose(torch.linalg.det(R), torch.ones(200, dtype=F64), atol=1e-14)
    back = matrix_to_axis_angle(R)
    assert back.norm(dim=-1).max() <= math.pi + 1e-12  # angle in [0, pi]
    err = (back - aa).norm(dim=-1)
    if angle > math.pi - 1e-6:  # at pi, a and -a are the same rotation
        err = torch.minimum(err, (back + aa).norm(dim=-1))
    assert err.max() < 1e-12, err.max()
    assert (axis_angle_to_matrix(back) - R).abs().max() < 1e-12


@pytest.mark.parametrize("angle", [1e-6, 0.5, 2.0, math.pi - 1e-3, math.pi - 1e-5, math.pi])
def test_axis_angle_round_trip_float32(angle):
    R = axis_angle_to_matrix((random_axes(200, seed=2) * angle).float())
    back = matrix_to_axis_angle(R)
    assert back.dtype == torch.float32
    assert (axis_angle_to_matrix(back) - R).abs().max() < 2e-6


def test_matrix_to_axis_angle_gradient_is_finite():
    aa = (random_axes(8, seed=3) * 0.7).requires_grad_()
    matrix_to_axis_angle(axis_angle_to_matrix(aa)).sum().backward()
    assert torch.isfinite(aa.grad).all() and torch.allclose(aa.grad, torch.ones_like(aa), atol=1e-10)


def test_rigid_inverse_and_transform_points():
    T = make_transform(axis_angle_to_matrix(random_axes(5, seed=4) * 1.3), torch.arange(15, dtype=F64).view(5, 3))
    assert torch.allclose(rigid_inverse(T) @ T, torch.eye(4, dtype=F64).expand(5, 4, 4), atol=1e-12)
    p = torch.tensor([0.5, -1.0, 2.0], dtype=F64)
    assert torch.allclose(transform_points(T, p), (T @ torch.cat([p, p.new_ones(1)]))[:, :3], atol=1e-12)


# ---- forward kinematics and blending ------------------------------------------------------------------------
def test_forward_kinematics_three_joint_chain():
    """Chain 0 -> 1 -> 2 along +y, joints 0 and 1 rotate 90 deg about z (hand-computed below)."""
    rest = torch.tensor([[1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [1.0, 2.0, 0.0]], dtype=F64)
    local = torch.stack([rot_z(90), rot_z(90), torch.eye(3, dtype=F64)])[None]  # [1, 3, 3, 3]
    shift = torch.tensor([[0.0, 0.0, 5.0]], dtype=F64)
    M = forward_kinematics(local, rest, (-1, 0, 1), root_translation=shift)[0]  # [3, 4, 4]
    # posed joints: j0 = (1,0,0); j1 = j0 + Rz90 (0,1,0) = (0,0,0); j2 = j1 + Rz180 (0,1,0) = (0,-1,0)
    # M_j = [R_world_j | posed_j - R_world_j rest_j] (+ shift)
    expected = [
        make_transform(rot_z(90), torch.tensor([1.0, -1.0, 5.0], dtype=F64)),
        make_transform(rot_z(180), torch.tensor([1.0, 1.0, 5.0], dtype=F64)),
        make_transform(rot_z(180), torch.tensor([1.0, 1.0, 5.0], dtype=F64)),
    ]
    for j in range(3):
        assert torch.allclose(M[j], expected[j], atol=1e-12), j
    posed = transform_points(M, rest)
    assert torch.allclose(posed, torch.tensor([[1.0, 0.0, 5.0], [0.0, 0.0, 5.0], [0.0, -1.0, 5.0]], dtype=F64),
                          atol=1e-12)
    # a point attached to joint 2, one unit further along the bone
    assert torch.allclose(transform_points(M[2], torch.tensor([1.0, 3.0, 0.0], dtype=F64)),
                          torch.tensor([0.0, -2.0, 5.0], dtype=F64), atol=1e-12)


def test_forward_kinematics_identity_pose_is_identity():
    rest = torch.randn(4, 3, dtype=F64)
    M = forward_kinematics(torch.eye(3, dtype=F64).expand(2, 4, 3, 3), rest, (-1, 0, 1, 1))
    assert torch.allclose(M, torch.eye(4, dtype=F64).expand(2, 4, 4, 4), atol=1e-12)


def test_blend_transforms_eq1_hand_example():
    M0 = make_transform(torch.eye(3, dtype=F64), torch.tensor([1.0, 0.0, 0.0], dtype=F64))
    M1 = make_transform(rot_z(90), torch.tensor([0.0, 2.0, 0.0], dtype=F64))
    M = torch.stack([M0, M1])[None]  # [1, 2, 4, 4]
    w = torch.tensor([[0.25, 0.75], [1.0, 0.0]], dtype=F64)
    T = blend_transforms(w, M)[0]  # [2, 4, 4]
    expected0 = torch.tensor([[0.25, -0.75, 0.0, 0.25], [0.75, 0.25, 0.0, 1.5], [0.0, 0.0, 1.0, 0.0],
                              [0.0, 0.0, 0.0, 1.0]], dtype=F64)
    assert torch.allclose(T[0], expected0, atol=1e-15)
    assert torch.allclose(T[1], M0, atol=1e-15)
    # Eq. 2 for the point (1, 0, 0) with the first weight row: T_0 p = (0.5, 2.25, 0)
    posed = lbs(torch.tensor([[1.0, 0.0, 0.0]], dtype=F64), w[:1], M)
    assert torch.allclose(posed, torch.tensor([[[0.5, 2.25, 0.0]]], dtype=F64), atol=1e-15)


def test_inverse_lbs_round_trip_random():
    g = torch.Generator().manual_seed(5)
    Fr, J, P = 3, 6, 500
    local = axis_angle_to_matrix(torch.randn(Fr, J, 3, generator=g, dtype=F64) * 0.6)
    M = forward_kinematics(local, torch.randn(J, 3, generator=g, dtype=F64) * 0.3, (-1, 0, 1, 2, 0, 4),
                           root_translation=torch.randn(Fr, 3, generator=g, dtype=F64))
    w = torch.rand(P, J, generator=g, dtype=F64) ** 4
    w = w / w.sum(1, keepdim=True)
    x = torch.randn(P, 3, generator=g, dtype=F64)
    back = inverse_lbs(lbs(x, w, M), w, M)
    assert (back - x).abs().max() < 1e-10  # float64


# ---- anny ------------------------------------------------------------------------------------------------------
def random_anny_motion(frames: int = 3, seed: int = 0) -> BodyMotion:
    from avatarctl.body.anny_model import identity_pose

    rng = np.random.default_rng(seed)
    pp = identity_pose(frames).astype(np.float64)
    rot = axis_angle_to_matrix(torch.as_tensor(rng.normal(0.0, 0.25, (frames, 104, 3)))).numpy()
    pp[:, :, :3, :3] = rot
    pp[:, 0, :3, 3] = rng.normal(0.0, 0.5, (frames, 3))  # root delta = world pose incl. position
    labels = ("gender", "age", "muscle", "weight", "height", "proportions")
    return BodyMotion(body_model="anny", frame_index=np.arange(frames), pose_parameters=pp,
                      phenotype=rng.uniform(0.2, 0.8, len(labels)), phenotype_labels=labels)


@pytest.fixture(scope="module")
def anny_body():
    pytest.importorskip("anny")
    from avatarctl.body.anny_model import AnnyBody

    return AnnyBody()


@pytest.mark.anny
def test_anny_wrapper_matches_anny_directly(anny_body):
    import anny

    motion = random_anny_motion()
    posed = anny_body.pose(motion)
    direct_model = anny.Anny()
    pheno = {lab: torch.tensor([float(v)], dtype=F64) for lab, v in zip(motion.phenotype_labels, motion.phenotype)}
    with torch.no_grad():
        direct = direct_model(pose_parameters=torch.as_tensor(motion.pose_parameters, dtype=F64),
                              phenotype_kwargs=pheno)["vertices"]
    assert posed.vertices.shape == (3, 13718, 3) and posed.vertices.dtype == torch.float32
    err = (posed.vertices.double() - direct).abs().max().item()
    assert err <= 1e-5, err
    # the phenotype is really used: a different phenotype moves the surface
    other = {lab: torch.tensor([0.5], dtype=F64) for lab in pheno}
    with torch.no_grad():
        neutral = direct_model(pose_parameters=torch.as_tensor(motion.pose_parameters, dtype=F64),
                               phenotype_kwargs=other)["vertices"]
    assert (neutral - direct).abs().max() > 1e-3


@pytest.mark.anny
def test_anny_lbs_of_template_reproduces_vertices(anny_body):
    motion = random_anny_motion(seed=1)
    tpl = anny_body.template(motion)
    posed = anny_body.pose(motion)
    J = len(tpl.parents)
    assert posed.joint_transforms.shape == (3, J, 4, 4) and posed.pose_features.shape == (3, J, 3)
    assert torch.all(posed.pose_features[:, 0] == 0)
    assert torch.allclose(tpl.skin_weights.sum(1), torch.ones(tpl.vertices.shape[0]), atol=1e-5)
    err = (lbs(tpl.vertices, tpl.skin_weights, posed.joint_transforms) - posed.vertices).abs().max().item()
    assert err <= 1e-5, err
    # inverse LBS brings the posed mesh back to the template (float64, weights renormalised)
    w = tpl.skin_weights.double()
    w = w / w.sum(1, keepdim=True)
    M = posed.joint_transforms.double()
    back = inverse_lbs(lbs(tpl.vertices.double(), w, M), w, M)
    err = (back - tpl.vertices.double()).abs().max().item()
    assert err <= 1e-9, err


@pytest.mark.anny
def test_anny_identity_pose_is_the_reference_pose(anny_body):
    from avatarctl.body.anny_model import identity_pose

    motion = BodyMotion(body_model="anny", frame_index=[0], pose_parameters=identity_pose(1))
    posed = anny_body.pose(motion)
    tpl = anny_body.template(motion)
    assert torch.all(posed.pose_features == 0)
    # the reference (A-)pose differs from the rest mesh by centimetres (FACTS.md: up to ~5.5 cm)
    gap = (posed.vertices[0] - tpl.vertices).norm(dim=-1).max().item()
    assert 0.01 < gap < 0.1, gap


@pytest.mark.anny
def test_anny_pose_parameters_from_joint_transforms(anny_body):
    """`motion_from_joint_transforms` inverts `pose` (round trip), and a rigid correction of one bone's subtree
    (what pose refinement applies) comes back as pose parameters whose forward kinematics give it."""
    motion = random_anny_motion(seed=2)
    posed = anny_body.pose(motion)
    back = anny_body.motion_from_joint_transforms(motion, posed.joint_transforms)
    assert np.abs(back.pose_parameters - motion.pose_parameters).max() <= 1e-5
    assert np.array_equal(back.phenotype, motion.phenotype) and np.array_equal(back.frame_index, motion.frame_index)
    D = make_transform(axis_angle_to_matrix(torch.tensor([0.1, 0.2, -0.1], dtype=F64)),
                       torch.tensor([0.01, 0.02, 0.0], dtype=F64))
    M = posed.joint_transforms.double().clone()
    M[1] = D @ M[1]  # every bone of frame 1 moved rigidly
    again = anny_body.pose(anny_body.motion_from_joint_transforms(motion, M))
    assert (again.joint_transforms.double() - M).abs().max() <= 1e-4
    assert (again.vertices[1] - posed.vertices[1]).norm(dim=-1).max() > 0.05  # really moved
    assert (again.vertices[0] - posed.vertices[0]).abs().max() <= 1e-4  # other frames untouched
    with pytest.raises(ValueError, match="joint_transforms must be"):
        anny_body.motion_from_joint_transforms(motion, M[:2])
