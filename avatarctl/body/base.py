"""The body-model interface every downstream stage uses.

Conventions: metres, float32 tensors, world frame of the capture. `joint_transforms[f, j]` is M_j(θ) of the
paper's Eq. 1: the rigid transform taking a point of the *canonical* (template) space, rigidly attached to
joint j, into the posed world space at frame f. Linear blend skinning of the canonical vertices with
`skin_weights` and these transforms reproduces the posed mesh (exactly for anny; for SMPL/SMPL-X up to the pose
blend shapes, which live in canonical space).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import torch

from avatarctl.body.motion import BodyMotion


@dataclass(frozen=True)
class BodyTemplate:
    """The canonical body of one subject (shape applied, canonical pose)."""

    name: str  # "anny" | "smpl" | "smplx"
    vertices: torch.Tensor  # [V, 3] canonical vertices, metres
    faces: torch.Tensor  # [F, 3] int64 triangle indices
    skin_weights: torch.Tensor  # [V, J] dense skinning weights, rows sum to 1
    parents: tuple[int, ...]  # [J] parent joint index, -1 for the root
    joint_names: tuple[str, ...]  # [J]

    def __post_init__(self) -> None:
        V, J = self.skin_weights.shape
        assert self.vertices.shape == (V, 3), f"vertices {tuple(self.vertices.shape)} vs weights {(V, J)}"
        assert self.faces.ndim == 2 and self.faces.shape[1] == 3, f"faces {tuple(self.faces.shape)}"
        assert len(self.parents) == J and len(self.joint_names) == J, f"{len(self.parents)} parents, {J} joints"

    @property
    def num_joints(self) -> int:
        return len(self.parents)


@dataclass(frozen=True)
class PosedBody:
    """A body model evaluated on a motion."""

    joint_transforms: torch.Tensor  # [frames, J, 4, 4] M_j(θ): canonical -> world (Eq. 1)
    vertices: torch.Tensor  # [frames, V, 3] posed vertices, world, metres
    pose_features: torch.Tensor  # [frames, J, 3] per-joint local rotation (axis-angle), root zeroed

    def __post_init__(self) -> None:
        F, J = self.joint_transforms.shape[:2]
        assert self.joint_transforms.shape == (F, J, 4, 4), f"joint_transforms {tuple(self.joint_transforms.shape)}"
        assert self.vertices.shape[0] == F and self.vertices.shape[-1] == 3, f"vertices {tuple(self.vertices.shape)}"
        assert self.pose_features.shape[:2] == (F, J), f"pose_features {tuple(self.pose_features.shape)}"


class BodyModel(Protocol):
    """What every body model provides."""

    name: str

    def template(self, motion: BodyMotion) -> BodyTemplate:
        """The canonical body for the subject whose shape parameters `motion` carries."""
        ...

    def pose(self, motion: BodyMotion) -> PosedBody:
        """Forward kinematics and skinning for every frame of `motion`."""
        ...
