"""Per-frame body-pose refinement (a deviation from the paper, issue 13; `ModelConfig.pose_refine`).

Real body fits are off by centimetres; an avatar trained on them blurs. Like HumanNeRF, InstantAvatar and GauHuman,
we optimise small per-frame corrections of the body pose jointly with the avatar. They act on the joint transforms
M_j(theta) (Eq. 1) of the training frames, so any body model works:

    x_j = M_j c_j                       the posed centre of joint j (c_j: canonical centre, `body.joints`)
    L_j = Rot(exp(delta_j)) about x_j   a small rotation of joint j about its centre (world-aligned axes)
    D_root = Trans(tau) L_root,  D_j = D_parent(j) L_j      corrections compose down the kinematic tree
    M'_j = D_j M_j

so rotating a joint moves everything below it, like a change of that joint's angle. delta [T, J, 3] (axis-angle,
radians) and tau [T, 3] (metres) start at zero for each of the T training frames and are pulled towards zero by
L_pose = lambda_pose * (sum_j |delta_j|^2 + |tau / 0.1 m|^2), averaged over the batch's frames. Frames the avatar
was not trained on (frame id -1) are left as they are. Only joints whose subtree (the joint and its descendants)
carries at least `model.pose_refine.min_share` of the template's skinning weight are refined (anny's fingers,
toes and face bones are too small in the images to correct and only drift); the others keep delta = 0. The
corrections live in the model's state, so `render` / `eval` of training frames use the refined poses.

No temporal smoothness term: an acceleration prior on the refined joint centres penalised the true motion too, and
where it is fast between frames it pulled the poses off (docs/fit.md, "Tried and removed").
"""

from __future__ import annotations

import torch
from torch import nn

from avatarctl.body.lbs import axis_angle_to_matrix


class PoseRefinement(nn.Module):
    """Per-training-frame joint rotation and root translation corrections (see the module docstring)."""

    def __init__(self, num_frames: int, parents: tuple[int, ...], active: torch.Tensor | None = None):
        super().__init__()
        J = len(parents)
        self.parents = tuple(int(p) for p in parents)
        self.levels = _levels(self.parents)
        self.register_buffer("is_root", torch.tensor([p < 0 for p in self.parents]), persistent=False)  # [J]
        self.delta = nn.Parameter(torch.zeros(num_frames, J, 3))  # [T, J, 3] axis-angle, radians
        self.tau = nn.Parameter(torch.zeros(num_frames, 3))  # [T, 3] root translation, metres
        self.register_buffer("centres", torch.zeros(J, 3))  # [J, 3] canonical joint centres c_j
        # [J] joints whose rotation is refined (the others keep delta = 0: too few pixels to correct them)
        self.register_buffer("active", torch.ones(J, dtype=torch.bool) if active is None else active.bool().clone())

    def set_centres(self, centres: torch.Tensor) -> None:
        """Store the canonical joint centres (`body.joints.joint_centres` of the training poses)."""
        self.centres.copy_(centres.to(self.centres))

    def forward(self, joint_transforms: torch.Tensor, frame_ids: torch.Tensor) -> torch.Tensor:
        """[B, J, 4, 4] M_j and [B] training-frame ids (-1: not a training frame) -> [B, J, 4, 4] M'_j."""
        train = frame_ids >= 0
        if not bool(train.any()):
            return joint_transforms
        M = joint_transforms
        Dr, Dtt = self._compose(M, frame_ids.clamp_min(0))
        out_R = Dr @ M[..., :3, :3]
        out_t = (Dr @ M[..., :3, 3:])[..., 0] + Dtt
        refined = torch.cat([torch.cat([out_R, out_t[..., None]], -1), M[..., 3:, :]], -2)
        return torch.where(train[:, None, None, None], refined, M)

    def _compose(self, M: torch.Tensor, ids: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The corrections D_j of the module docstring for [B, J, 4, 4] transforms M of frames `ids` [B] ->
        (rotations [B, J, 3, 3], translations [B, J, 3])."""
        dt = M.dtype
        R = axis_angle_to_matrix((self.delta[ids] * self.active[:, None]).to(dt))  # [B, J, 3, 3]
        x = (M[..., :3, :3] @ self.centres.to(dt)[None, :, :, None])[..., 0] + M[..., :3, 3]  # [B, J, 3] x_j
        t = x - (R @ x[..., None])[..., 0]  # [B, J, 3]: rotation about x_j
        t = t + self.is_root[None, :, None] * self.tau[ids].to(dt)[:, None, :]  # the root also moves by tau
        Dr, Dtt = R, t  # [B, J, 3, 3], [B, J, 3]: D_j for the joints composed so far (the roots: L_root)
        for lv, par in self.levels:
            lv, par = lv.to(M.device), par.to(M.device)
            Rp, tp = Dr[:, par], Dtt[:, par]  # parents are one level up: already composed
            Dr = Dr.index_copy(1, lv, Rp @ R[:, lv])
            Dtt = Dtt.index_copy(1, lv, (Rp @ t[:, lv, :, None])[..., 0] + tp)
        return Dr, Dtt

    def penalty(self, frame_ids: torch.Tensor) -> torch.Tensor:
        """Mean over the batch's training frames of sum_j |delta_j|^2 + |tau / 0.1 m|^2 (radians^2; 0.1 m makes
        1 cm weigh like 0.1 rad); zero when the batch has none."""
        ids = frame_ids[frame_ids >= 0]
        if not len(ids):
            return self.delta.new_zeros(())
        rot = ((self.delta[ids] * self.active[:, None]) ** 2).sum((-1, -2))
        return (rot + ((self.tau[ids] / 0.1) ** 2).sum(-1)).mean()


def subtree_share(skin_weights: torch.Tensor, parents: tuple[int, ...]) -> torch.Tensor:
    """[V, J] template skinning weights -> [J] share of the total weight carried by each joint and its descendants
    (what a rotation of that joint moves)."""
    sub = skin_weights.double().sum(0)
    for j in sorted(range(len(parents)), key=lambda j: -_depth(parents, j)):  # children before parents
        if parents[j] >= 0:
            sub[parents[j]] += sub[j]
    return (sub / skin_weights.double().sum()).to(skin_weights.dtype)


def _levels(parents: tuple[int, ...]) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """Joints grouped by tree depth below the roots, (joints of the level, their parents), so the composition down
    the tree is one batched product per level."""
    depth = [_depth(parents, j) for j in range(len(parents))]
    levels = [[j for j in range(len(parents)) if depth[j] == d] for d in range(1, max(depth, default=0) + 1)]
    return [(torch.tensor(lv), torch.tensor([parents[j] for j in lv])) for lv in levels]


def _ancestry(parents: tuple[int, ...], j: int) -> list[int]:
    """j and its ancestors up to the root."""
    out = [j]
    while parents[out[-1]] >= 0:
        out.append(parents[out[-1]])
    return out


def _depth(parents: tuple[int, ...], j: int) -> int:
    return len(_ancestry(parents, j)) - 1
