"""A tiny synthetic body for tests and quick experiments: a sphere "body" with two joints.

Joint 0 (root) holds the lower hemisphere, joint 1 the upper one, with weights blended smoothly across the
equator; joint 1 bends about the +x axis through the sphere centre. Metres; no licensed data.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from avatarctl.body.base import BodyTemplate
from avatarctl.body.lbs import axis_angle_to_matrix, make_transform


def sphere_template(num_vertices: int = 400, radius: float = 0.3) -> BodyTemplate:
    """Fibonacci-sphere vertices (deterministic), convex-hull faces, 2-joint skinning weights."""
    from scipy.spatial import ConvexHull

    k = np.arange(num_vertices) + 0.5
    z = 1.0 - 2.0 * k / num_vertices
    phi = k * math.pi * (3.0 - math.sqrt(5.0))
    r = np.sqrt(1.0 - z * z)
    v = np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=-1) * radius
    faces = ConvexHull(v).simplices
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
