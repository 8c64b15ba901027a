"""Per-frame conditioning of the model: body joint transforms, pose features and the time stamp t/T.

Time stamp (supplement): the t-th training frame (0-based, training frames sorted by capture frame number, which is
their time order) gets t / T, T = number of training frames, so time is in [0, 1). `frame_ids` is t for training
frames (used by the "per_frame" latent ablation) and -1 for frames the model was not trained on (novel poses, whose
time is set to 0; the "zero" latent mode ignores it).

`PoseTable` holds what training needs for every training frame without the posed meshes: the body's joint
transforms M_j(theta) (Eq. 1), its pose features and the axis-aligned 3D box of the posed vertices. For a
THuman4-sized capture (5,000 frames, anny's 104 joints) that is ~35 MB, where the posed meshes would be ~820 MB.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from avatarctl.body.base import BodyModel
from avatarctl.body.motion import BodyMotion
from avatarctl.model.avatar import FrameConditioning


@dataclass(frozen=True)
class PoseTable:
    """Body-model quantities for a list of frames (rows follow `frames`)."""

    frames: tuple[int, ...]  # [frames] capture frame numbers
    joint_transforms: torch.Tensor  # [frames, J, 4, 4] M_j(theta): canonical -> world (Eq. 1), float32, CPU
    pose_features: torch.Tensor  # [frames, J, 3] per-joint local axis-angle, root zeroed
    box_lo: np.ndarray  # [frames, 3] min corner of the posed vertices, world, metres
    box_hi: np.ndarray  # [frames, 3] max corner

    def rows(self, frames: list[int] | np.ndarray) -> np.ndarray:
        lookup = {f: i for i, f in enumerate(self.frames)}
        return np.array([lookup[int(f)] for f in frames], dtype=np.int64)


def build_pose_table(body: BodyModel, motion: BodyMotion, frames: list[int], chunk: int = 128) -> PoseTable:
    """Pose `frames` (capture frame numbers) in chunks, keeping transforms, pose features and boxes only."""
    rows = motion.rows_for(frames)
    jt, pf, lo, hi = [], [], [], []
    for s in range(0, len(rows), chunk):
        posed = body.pose(motion.select(rows[s:s + chunk]))
        jt.append(posed.joint_transforms.detach().float().cpu())
        pf.append(posed.pose_features.detach().float().cpu())
        v = posed.vertices.detach().float().cpu()
        lo.append(v.amin(dim=1).numpy())
        hi.append(v.amax(dim=1).numpy())
    return PoseTable(frames=tuple(int(f) for f in frames), joint_transforms=torch.cat(jt), pose_features=torch.cat(pf),
                     box_lo=np.concatenate(lo).astype(np.float64), box_hi=np.concatenate(hi).astype(np.float64))


def time_stamps(frames: list[int] | np.ndarray, train_frames: list[int], are_training: bool
                ) -> tuple[torch.Tensor, torch.Tensor]:
    """(time [B] float32 = t/T, frame_ids [B] long = t) for training frames; (0, -1) for novel frames.

    With `are_training`, every frame must be one of `train_frames` (a `KeyError` names the one that is not).
    """
    n = len(frames)
    if not are_training:
        return torch.zeros(n, dtype=torch.float32), torch.full((n,), -1, dtype=torch.long)
    index = {int(f): t for t, f in enumerate(sorted(int(f) for f in train_frames))}
    try:
        ids = [index[int(f)] for f in frames]
    except KeyError as e:
        raise KeyError(f"frame {e.args[0]} is not a training frame of this avatar") from None
    T = len(index)
    return (torch.tensor(ids, dtype=torch.float32) / T, torch.tensor(ids, dtype=torch.long))


def make_conditioning(joint_transforms: torch.Tensor, pose_features: torch.Tensor, time: torch.Tensor,
                      frame_ids: torch.Tensor, device: str | torch.device) -> FrameConditioning:
    """Bundle [B, J, 4, 4], [B, J, 3], [B], [B] into a `FrameConditioning` on `device`."""
    return FrameConditioning(joint_transforms=joint_transforms.to(device=device, dtype=torch.float32),
                             pose_features=pose_features.to(device=device, dtype=torch.float32),
                             time=time.to(device=device, dtype=torch.float32),
                             frame_ids=frame_ids.to(device=device, dtype=torch.long))


def conditioning_for_motion(body: BodyModel, motion: BodyMotion, train_frames: list[int], are_training: bool,
                            device: str | torch.device) -> FrameConditioning:
    """Conditioning for every row of `motion` (see `time_stamps` for the time stamp rule)."""
    posed = body.pose(motion)
    time, ids = time_stamps(motion.frame_index, train_frames, are_training)
    return make_conditioning(posed.joint_transforms, posed.pose_features, time, ids, device)
