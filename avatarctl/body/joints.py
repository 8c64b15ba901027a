"""Joint centres and posed joints of any skinned body model, from its joint transforms alone.

The `BodyModel` interface gives M_j(theta) (canonical -> world, Eq. 1) per joint, not the joints' positions. The
canonical centre c_j of joint j is the point its transform and its parent's agree on whatever the pose (a joint
rotates about its centre): M_p(theta) c_j = M_j(theta) c_j for every frame. `joint_centres` solves that in least
squares over the given frames, with a small pull towards a fallback (the skin-weighted centroid of the joint's
vertices) for joints that barely move in those frames (ill-posed there). Posed joints are then M_j(theta) c_j.
"""

from __future__ import annotations

import torch


def skin_weighted_centroids(vertices: torch.Tensor, skin_weights: torch.Tensor) -> torch.Tensor:
    """[V, 3] canonical vertices, [V, J] weights -> [J, 3] weight-averaged vertex of each joint (the fallback)."""
    w = skin_weights.double()
    mass = w.sum(0).clamp_min(1e-9)
    centroid = (w.T @ vertices.double()) / mass[:, None]
    empty = w.sum(0) < 1e-9
    centroid[empty] = vertices.double().mean(0)
    return centroid.to(vertices.dtype)


def joint_centres(joint_transforms: torch.Tensor, parents: tuple[int, ...], fallback: torch.Tensor,
                  ridge: float = 1e-3) -> torch.Tensor:
    """[F, J, 4, 4] transforms of F frames -> [J, 3] canonical joint centres (see the module docstring).

    Minimises sum_f |(M_p - M_j) [c; 1]|^2 + ridge * F * |c - fallback_j|^2 for each joint with a parent; the root
    gets its fallback.
    """
    M = joint_transforms.double()
    F, J = M.shape[:2]
    fb = fallback.double()
    out = fb.clone()
    for j, p in enumerate(parents):
        if p < 0:
            continue
        A = (M[:, p, :3, :3] - M[:, j, :3, :3]).reshape(3 * F, 3)  # [3F, 3]
        b = (M[:, j, :3, 3] - M[:, p, :3, 3]).reshape(3 * F)
        lhs = A.T @ A + ridge * F * torch.eye(3, dtype=M.dtype)
        rhs = A.T @ b + ridge * F * fb[j]
        out[j] = torch.linalg.solve(lhs, rhs)
    return out.to(joint_transforms.dtype)


def posed_joints(joint_transforms: torch.Tensor, centres: torch.Tensor) -> torch.Tensor:
    """[..., J, 4, 4] transforms and [J, 3] canonical centres -> [..., J, 3] world joint positions."""
    return (joint_transforms[..., :3, :3] @ centres[..., None])[..., 0] + joint_transforms[..., :3, 3]


MAJOR_JOINT_SHARE = 0.01  # a "major" joint carries at least this share of the template's skinning weight


def major_joints(skin_weights: torch.Tensor) -> torch.Tensor:
    """[J] bool: the joints carrying at least `MAJOR_JOINT_SHARE` of the skinning weight `skin_weights` [V, J] (14 for
    anny: hips, feet, spine, upper / lower arms, head; fingers and face bones are not), the joints the benchmarks'
    joint errors are over."""
    mass = skin_weights.sum(0)
    return mass > MAJOR_JOINT_SHARE * mass.sum()
