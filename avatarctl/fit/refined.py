"""The refined body fits of a fit with pose refinement (model/pose_refine.py, issue 13), as a motion file.

After training, the corrected joint transforms M'_j = D_j M_j of every training frame are turned back into the body
model's pose parameters (`motion_from_joint_transforms` of the body model: anny's local-ref deltas, exact; SMPL /
SMPL-X global_orient, body_pose (SMPL-X also jaw, eyes, hands) and transl with betas and expression kept, rotations
exact) and written as `fit/refined_fits.npz`, a `BodyMotion` that `render --poses`, `export` and other tools read like
any motion file. The frame index is the training frames'. Body models without that inverse (the toy body) get no
file: their refined poses still live in the checkpoint and are used by `render` / `eval` of training frames.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from avatarctl.body.motion import BodyMotion
from avatarctl.fit.conditioning import PoseTable
from avatarctl.model.pose_refine import PoseRefinement

FILE_NAME = "refined_fits.npz"


@dataclass(frozen=True)
class RefinementSummary:
    """How far the refinement moved the fits (means over training frames; rotations over the refined joints)."""

    frames: int
    joints: int  # joints whose rotation is refined
    mean_rotation_deg: float  # mean |delta_j| over frames and refined joints
    max_rotation_deg: float
    mean_root_shift_cm: float  # mean |tau| over frames
    path: Path | None  # the motion file, None when the body model cannot invert its joint transforms

    def to_json(self) -> dict[str, object]:
        return {"frames": self.frames, "joints": self.joints, "mean_rotation_deg": round(self.mean_rotation_deg, 4),
                "max_rotation_deg": round(self.max_rotation_deg, 4),
                "mean_root_shift_cm": round(self.mean_root_shift_cm, 4),
                "path": None if self.path is None else str(self.path)}


def refined_motion(body: object, motion: BodyMotion, poses: PoseTable, refine: PoseRefinement) -> BodyMotion | None:
    """The training frames' refined fits as a `BodyMotion` (rows follow `poses.frames`), or None when `body` has
    no `motion_from_joint_transforms`."""
    invert = getattr(body, "motion_from_joint_transforms", None)
    if invert is None:
        return None
    ids = torch.arange(len(poses.frames))
    with torch.no_grad():
        M = refine(poses.joint_transforms.to(refine.delta.device).double(), ids.to(refine.delta.device))
    sub = motion.for_frames(list(poses.frames))
    return invert(sub, M.cpu())


def summarise(refine: PoseRefinement, path: Path | None) -> RefinementSummary:
    with torch.no_grad():
        active = refine.active.bool()
        ang = refine.delta.detach().norm(dim=-1)[:, active].double() * (180.0 / math.pi)  # [T, J_active]
        shift = refine.tau.detach().norm(dim=-1).double() * 100.0
    return RefinementSummary(frames=int(refine.delta.shape[0]), joints=int(active.sum()),
                             mean_rotation_deg=float(ang.mean()) if ang.numel() else 0.0,
                             max_rotation_deg=float(ang.max()) if ang.numel() else 0.0,
                             mean_root_shift_cm=float(shift.mean()), path=path)


def write_refined_fits(fit_dir: Path, body: object, motion: BodyMotion, poses: PoseTable,
                       refine: PoseRefinement) -> RefinementSummary:
    """Write `fit_dir/refined_fits.npz` (atomically) when the body model can invert its transforms."""
    m = refined_motion(body, motion, poses, refine)
    path = None
    if m is not None:
        path = fit_dir / FILE_NAME
        m.save(path, extra={"provenance": np.array("avatarctl fit: pose refinement (model/pose_refine.py)")})
    return summarise(refine, path)
