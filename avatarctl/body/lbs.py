"""Pure functions for rotations, forward kinematics and linear blend skinning (Eq. 1-2 of the paper).

All functions are batched over leading dimensions and differentiable.
"""

from __future__ import annotations

import torch


def axis_angle_to_matrix(aa: torch.Tensor) -> torch.Tensor:
    """Rodrigues' formula. [..., 3] axis-angle (radians) -> [..., 3, 3]."""
    angle = aa.norm(dim=-1, keepdim=True)  # [..., 1]
    small = angle < 1e-8
    axis = aa / torch.where(small, torch.ones_like(angle), angle)
    x, y, z = axis.unbind(-1)
    zero = torch.zeros_like(x)
    Kx = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], dim=-1).reshape(*aa.shape[:-1], 3, 3)
    s = torch.sin(angle)[..., None]
    c = torch.cos(angle)[..., None]
    eye = torch.eye(3, dtype=aa.dtype, device=aa.device).expand_as(Kx)
    R = eye + s * Kx + (1 - c) * (Kx @ Kx)
    # first-order expansion near zero keeps gradients finite
    Kaa = torch.stack([zero, -aa[..., 2], aa[..., 1], aa[..., 2], zero, -aa[..., 0], -aa[..., 1], aa[..., 0], zero],
                      dim=-1).reshape(*aa.shape[:-1], 3, 3)
    return torch.where(small[..., None], eye + Kaa, R)


def matrix_to_axis_angle(R: torch.Tensor) -> torch.Tensor:
    """[..., 3, 3] rotation matrices -> [..., 3] axis-angle (radians, angle in [0, pi]).

    angle = atan2(|v| / 2, (tr R - 1) / 2) with v the antisymmetric part (v = 2 sin(angle) axis), which stays
    accurate near 0 and pi (acos does not). For angles above pi/2 the axis comes from the symmetric part,
    (R + R^T) / 2 - cos(angle) I = (1 - cos(angle)) axis axis^T, whose accuracy does not degrade near pi.
    """
    cos = (R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2] - 1) / 2
    v = torch.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], dim=-1)
    sin = v.norm(dim=-1) / 2
    angle = torch.atan2(sin, cos)
    small = sin < 1e-12
    scale = torch.where(small, torch.full_like(sin, 0.5), angle / (2 * torch.where(small, torch.ones_like(sin), sin)))
    out = v * scale[..., None]  # near zero angle / (2 sin) -> 1/2
    obtuse = cos < 0
    if obtuse.any():
        S = (R + R.transpose(-1, -2)) / 2 - cos[..., None, None] * torch.eye(3, dtype=R.dtype, device=R.device)
        i = torch.diagonal(S, dim1=-2, dim2=-1).argmax(dim=-1, keepdim=True)
        col = torch.gather(S, -1, i[..., None, :].expand(*S.shape[:-1], 1)).squeeze(-1)
        axis = col / col.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        sign = torch.sign((axis * v).sum(-1, keepdim=True))
        sign = torch.where(sign == 0, torch.ones_like(sign), sign)
        out = torch.where(obtuse[..., None], axis * sign * angle[..., None], out)
    return out


def make_transform(R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """[..., 3, 3], [..., 3] -> [..., 4, 4] homogeneous transform."""
    top = torch.cat([R, t[..., None]], dim=-1)
    bottom = torch.zeros(*R.shape[:-2], 1, 4, dtype=R.dtype, device=R.device)
    bottom[..., 0, 3] = 1
    return torch.cat([top, bottom], dim=-2)


def transform_points(T: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """Apply [..., 4, 4] transforms to [..., 3] points (broadcasting)."""
    return (T[..., :3, :3] @ p[..., None]).squeeze(-1) + T[..., :3, 3]


def rigid_inverse(T: torch.Tensor) -> torch.Tensor:
    """Inverse of [..., 4, 4] rigid transforms."""
    Rt = T[..., :3, :3].transpose(-1, -2)
    return make_transform(Rt, -(Rt @ T[..., :3, 3:]).squeeze(-1))


def forward_kinematics(local_rot: torch.Tensor, rest_joints: torch.Tensor, parents: tuple[int, ...] | list[int],
                       root_translation: torch.Tensor | None = None) -> torch.Tensor:
    """SMPL-style forward kinematics.

    Args:
        local_rot: [frames, J, 3, 3] rotation of each joint relative to its parent (root: global orientation).
        rest_joints: [J, 3] or [frames, J, 3] joint locations in the canonical pose.
        parents: [J] parent indices (-1 for the root); parents precede children.
        root_translation: [frames, 3] translation added to every transform.

    Returns:
        [frames, J, 4, 4] transforms M_j mapping canonical points attached to joint j to the posed space
        (the rest joint location is removed, so `M_j @ rest_joint_j` = posed joint j).
    """
    F, J = local_rot.shape[:2]
    if rest_joints.ndim == 2:
        rest_joints = rest_joints.expand(F, J, 3)
    rel = rest_joints.clone()
    par = torch.as_tensor([max(p, 0) for p in parents], device=rest_joints.device)
    rel[:, 1:] = rest_joints[:, 1:] - rest_joints[:, par[1:]]
    local = make_transform(local_rot, rel)  # [F, J, 4, 4]
    world = [local[:, 0]]
    for j in range(1, J):
        world.append(world[parents[j]] @ local[:, j])
    G = torch.stack(world, dim=1)  # [F, J, 4, 4]
    posed_joints = G[..., :3, 3]
    # remove the rest joint location: M_j = G_j * translate(-rest_joint_j)
    t = posed_joints - (G[..., :3, :3] @ rest_joints[..., None]).squeeze(-1)
    if root_translation is not None:
        t = t + root_translation[:, None, :]
    return make_transform(G[..., :3, :3], t)


def blend_transforms(weights: torch.Tensor, joint_transforms: torch.Tensor) -> torch.Tensor:
    """Eq. 1: T_i = sum_j w_ij M_j(θ).

    Args:
        weights: [P, J] skinning weights of P points (vertices or nodes).
        joint_transforms: [frames, J, 4, 4].
    Returns:
        [frames, P, 4, 4] blended (generally non-rigid) transforms.
    """
    F, J = joint_transforms.shape[:2]
    assert weights.shape[-1] == J, f"weights {tuple(weights.shape)} vs {J} joints"
    return torch.einsum("pj,fjab->fpab", weights.to(joint_transforms.dtype), joint_transforms)


def lbs(points: torch.Tensor, weights: torch.Tensor, joint_transforms: torch.Tensor) -> torch.Tensor:
    """Eq. 2: posed point = T_i @ canonical point.

    [P, 3] (or [frames, P, 3]), [P, J], [frames, J, 4, 4] -> [frames, P, 3]."""
    T = blend_transforms(weights, joint_transforms)
    return transform_points(T, points.to(T.dtype))


def inverse_lbs(posed: torch.Tensor, weights: torch.Tensor, joint_transforms: torch.Tensor) -> torch.Tensor:
    """Map posed points back to canonical space with the inverse of their blended transform. -> [frames, P, 3]."""
    T = blend_transforms(weights, joint_transforms)
    # solve A x = y - t on the 3x3 block: exact even when float32 weights do not sum to exactly 1
    rhs = (posed.to(T.dtype) - T[..., :3, 3])[..., None]
    return torch.linalg.solve(T[..., :3, :3], rhs).squeeze(-1)
