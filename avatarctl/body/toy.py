"""A tiny synthetic body for tests and quick experiments: a sphere "body" with two joints (`--body-model toy`).

Joint 0 (root) holds the lower hemisphere, joint 1 the upper one, with weights blended smoothly across the
equator; joint 1 bends about the +x axis through the sphere centre. Metres; no licensed data.

`ToyBody` is a full `BodyModel` (registered as "toy" in `body.registry`): a whole ingest -> fit -> render -> eval
chain runs on it in seconds, without anny's cache. Its motion (`BodyMotion(body_model="toy")`) carries
`global_orient` [frames, 3] (root rotation about the sphere centre), `body_pose` [frames, 3] (joint 1, axis-angle,
relative to the root) and `transl` [frames, 3] (metres).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from avatarctl.body.base import BodyTemplate, PosedBody
from avatarctl.body.lbs import axis_angle_to_matrix, lbs, make_transform
from avatarctl.body.motion import BodyMotion


def sphere_template(num_vertices: int = 400, radius: float = 0.3) -> BodyTemplate:
    """Fibonacci-sphere vertices (deterministic), convex-hull faces wound counter-clockwise seen from outside (as a
    body model's: the signed volume is positive), 2-joint skinning weights."""
    from scipy.spatial import ConvexHull

    k = np.arange(num_vertices) + 0.5
    z = 1.0 - 2.0 * k / num_vertices
    phi = k * math.pi * (3.0 - math.sqrt(5.0))
    r = np.sqrt(1.0 - z * z)
    v = np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=-1) * radius
    faces = ConvexHull(v).simplices
    a, b, c = v[faces[:, 0]], v[faces[:, 1]], v[faces[:, 2]]
    inward = np.einsum("ij,ij->i", np.cross(b - a, c - a), a + b + c) < 0  # the centre is the origin
    faces[inward] = faces[inward][:, ::-1]
    w1 = 1.0 / (1.0 + np.exp(-v[:, 2] / (0.2 * radius)))  # upper hemisphere -> joint 1
    weights = np.stack([1.0 - w1, w1], axis=-1)
    return BodyTemplate(name="toy", vertices=torch.tensor(v, dtype=torch.float32),
                        faces=torch.tensor(faces, dtype=torch.int64),
                        skin_weights=torch.tensor(weights, dtype=torch.float32), parents=(-1, 0),
                        joint_names=("root", "upper"))


def toy_joint_transforms(bend: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """bend [B] radians about +x -> (joint_transforms [B, 2, 4, 4], pose_features [B, 2, 3]); root = identity."""
    B = bend.shape[0]
    aa = torch.zeros(B, 2, 3, dtype=torch.float32)
    aa[:, 1, 0] = bend
    M = make_transform(axis_angle_to_matrix(aa), torch.zeros(B, 2, 3))
    return M, aa


class ToyBody:
    """The sphere body as a `BodyModel` (no shape parameters: every subject is the same sphere)."""

    name = "toy"

    def __init__(self, num_vertices: int = 400, radius: float = 0.3):
        self._template = sphere_template(num_vertices, radius)

    def template(self, motion: BodyMotion) -> BodyTemplate:
        return self._template

    def pose(self, motion: BodyMotion) -> PosedBody:
        """M_0 = [R(global_orient) | transl], M_1 = M_0 [R(body_pose) | 0] (both joints pivot at the centre)."""
        go = torch.as_tensor(motion.global_orient, dtype=torch.float32)  # [frames, 3]
        bend = torch.as_tensor(motion.body_pose, dtype=torch.float32)  # [frames, 3]
        transl = torch.as_tensor(motion.transl, dtype=torch.float32)  # [frames, 3]
        M0 = make_transform(axis_angle_to_matrix(go), transl)  # [frames, 4, 4]
        M1 = M0 @ make_transform(axis_angle_to_matrix(bend), torch.zeros_like(transl))
        M = torch.stack([M0, M1], dim=1)  # [frames, 2, 4, 4]
        verts = lbs(self._template.vertices, self._template.skin_weights, M)  # [frames, V, 3]
        feats = torch.stack([torch.zeros_like(bend), bend], dim=1)  # [frames, 2, 3], root zeroed
        return PosedBody(joint_transforms=M, vertices=verts, pose_features=feats)
