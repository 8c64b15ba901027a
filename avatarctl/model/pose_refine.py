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
L_pose = lambda_pose * (sum_j |delta_j|^2 + |tau / 0.1 m|^2), averaged over the batch's frames,. Frames the avatar was not trained on (frame id -1)
are left as they are. Only joints whose subtree (the joint and its descendants) carries at least
`ModelConfig.pose_refine_min_share` of the template's skinning weight are refined (anny's fingers, toes and face bones are too small in the images to correct and only
drift); the others keep delta = 0. The corrections live in the model's state, so `render` / `eval` of training frames use the
refined poses.

Temporal smoothness (`ModelConfig.lambda_pose_accel` > 0, off by default): fits from per-frame estimates jitter from
frame to frame, and the prior above pulls each frame towards its own jittered fit. With the unrefined M_j of every
training frame (`set_sequence`), the acceleration of the refined joint centres x'_j = M'_j c_j over each triple of
training frames equally spaced in time,

    L_accel = mean over triples (t-1, t, t+1) of sum_j |x'_j(t-1) - 2 x'_j(t) + x'_j(t+1)|^2    (metres^2, refined j)

is added once per step with weight lambda_pose_accel, so every frame's correction gets a gradient every step. The
images decide where the motion really is fast; a triple across a gap in the training frames is not penalised.
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
        depth = [_depth(self.parents, j) for j in range(J)]
        # joints grouped by tree depth, so the composition down the tree is one batched product per level:
        # (joints of the level, their parents) below the roots, built once
        levels = [[j for j in range(J) if depth[j] == d] for d in range(1, max(depth) + 1)]
        self.levels = [(torch.tensor(lv), torch.tensor([self.parents[j] for j in lv])) for lv in levels]
        self.register_buffer("is_root", torch.tensor([p < 0 for p in self.parents]), persistent=False)  # [J]
        self.delta = nn.Parameter(torch.zeros(num_frames, J, 3))  # [T, J, 3] axis-angle, radians
        self.tau = nn.Parameter(torch.zeros(num_frames, 3))  # [T, 3] root translation, metres
        self.register_buffer("centres", torch.zeros(J, 3))  # [J, 3] canonical joint centres c_j
        # [J] joints whose rotation is refined (the others keep delta = 0: too few pixels to correct them)
        self.register_buffer("active", torch.ones(J, dtype=torch.bool) if active is None else active.bool().clone())
        # the whole sequence for the smoothness term (`set_sequence`; rebuilt from the capture, not checkpointed)
        self.register_buffer("base", torch.zeros(0, J, 4, 4), persistent=False)  # [T, J, 4, 4] unrefined M_j
        self.register_buffer("triples", torch.zeros(0, 3, dtype=torch.long), persistent=False)  # [K, 3] frame slots

    def set_centres(self, centres: torch.Tensor) -> None:
        """Store the canonical joint centres (`body.joints.joint_centres` of the training poses)."""
        self.centres.copy_(centres.to(self.centres))

    def set_sequence(self, joint_transforms: torch.Tensor, frames: list[int]) -> None:
        """[T, J, 4, 4] unrefined M_j of the T training frames (slot order) and their frame numbers [T]: the
        sequence `acceleration` smooths; triples are consecutive slots whose frame numbers are equally spaced."""
        if joint_transforms.shape[0] != self.delta.shape[0] or len(frames) != self.delta.shape[0]:
            raise ValueError(f"set_sequence needs the {self.delta.shape[0]} training frames, got "
                             f"{joint_transforms.shape[0]} transforms and {len(frames)} frame numbers")
        f = [int(x) for x in frames]
        triples = [(t - 1, t, t + 1) for t in range(1, len(f) - 1) if f[t] - f[t - 1] == f[t + 1] - f[t] > 0]
        self.base = joint_transforms.detach().to(self.delta.device, torch.float32).clone()
        self.triples = torch.tensor(triples, dtype=torch.long, device=self.delta.device).reshape(-1, 3)

    def acceleration(self) -> torch.Tensor:
        """L_accel of the module docstring (metres^2); zero when `set_sequence` found no equally spaced triple."""
        if not len(self.triples):
            return self.delta.new_zeros(())
        M = self(self.base, torch.arange(self.base.shape[0], device=self.base.device))  # [T, J, 4, 4] M'_j
        x = (M[..., :3, :3] @ self.centres[None, :, :, None])[..., 0] + M[..., :3, 3]  # [T, J, 3] x'_j
        a = x[self.triples[:, 0]] - 2 * x[self.triples[:, 1]] + x[self.triples[:, 2]]  # [K, J, 3]
        return (a[:, self.active] ** 2).sum((-1, -2)).mean()

    def forward(self, joint_transforms: torch.Tensor, frame_ids: torch.Tensor) -> torch.Tensor:
        """[B, J, 4, 4] M_j and [B] training-frame ids (-1: not a training frame) -> [B, J, 4, 4] M'_j."""
        train = frame_ids >= 0
        if not bool(train.any()):
            return joint_transforms
        M = joint_transforms
        ids = frame_ids.clamp_min(0)
        dt = M.dtype
        R = axis_angle_to_matrix((self.delta[ids] * self.active[:, None]).to(dt))  # [B, J, 3, 3]
        x = (M[..., :3, :3] @ self.centres.to(dt)[None, :, :, None])[..., 0] + M[..., :3, 3]  # [B, J, 3] x_j
        t = x - (R @ x[..., None])[..., 0]  # [B, J, 3]: rotation about x_j
        t = t + self.is_root[None, :, None] * self.tau[ids].to(dt)[:, None, :]  # the root also translates by tau
        Dr, Dtt = R, t  # [B, J, 3, 3], [B, J, 3]: D_j for the joints composed so far (the roots: L_root)
        for lv, par in self.levels:
            lv, par = lv.to(M.device), par.to(M.device)
            Rp, tp = Dr[:, par], Dtt[:, par]  # parents are one level up: already composed
            Dr = Dr.index_copy(1, lv, Rp @ R[:, lv])
            Dtt = Dtt.index_copy(1, lv, (Rp @ t[:, lv, :, None])[..., 0] + tp)
        out_R = Dr @ M[..., :3, :3]
        out_t = (Dr @ M[..., :3, 3:])[..., 0] + Dtt
        refined = torch.cat([torch.cat([out_R, out_t[..., None]], -1), M[..., 3:, :]], -2)
        return torch.where(train[:, None, None, None], refined, M)

    def penalty(self, frame_ids: torch.Tensor) -> torch.Tensor:
        """Mean over the batch's training frames of sum_j |delta_j|^2 + |tau / 0.1 m|^2 (radians^2; 0.1 m makes
        1 cm weigh like 0.1 rad); zero when the batch has none."""
        ids = frame_ids[frame_ids >= 0]
        if not len(ids):
            return self.delta.new_zeros(())
        return (((self.delta[ids] * self.active[:, None]) ** 2).sum((-1, -2)) + ((self.tau[ids] / 0.1) ** 2).sum(-1)).mean()


def subtree_share(skin_weights: torch.Tensor, parents: tuple[int, ...]) -> torch.Tensor:
    """[V, J] template skinning weights -> [J] share of the total weight carried by each joint and its descendants
    (what a rotation of that joint moves)."""
    sub = skin_weights.double().sum(0)
    for j in sorted(range(len(parents)), key=lambda j: -_depth(parents, j)):  # children before parents
        if parents[j] >= 0:
            sub[parents[j]] += sub[j]
    return (sub / skin_weights.double().sum()).to(skin_weights.dtype)


def _depth(parents: tuple[int, ...], j: int) -> int:
    d = 0
    while parents[j] >= 0:
        j = parents[j]
        d += 1
    return d
