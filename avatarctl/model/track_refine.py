"""Per-frame corrections of the tracked garment nodes (a deviation from the paper, issue 48;
`ModelConfig.track_refine`, docs/fit.md "Garment tracking").

The garment tracker (fit/garment_track.py) places each tracked hull node i on training frame f at a rotation R_fi
and a centre c_fi (`SlrfAvatar.set_tracks`); it is a few centimetres off the cloth, and the error drifts over the
frames. Like the per-frame body-pose corrections (model/pose_refine.py), a small rigid correction per training frame
and node is learned with the avatar, from the images:

    R'_fi = Rot(exp(w_fi)) R_fi         c'_fi = c_fi + d_fi

w [F, N, 3] (axis-angle, radians) and d [F, N, 3] (metres) start at zero (the tracks as they are); only the tracked
nodes' rows are used. Two priors hold them:

    L_refine = lambda_size   * mean_f in batch  sum_i (|d_fi|^2 + (s |w_fi|)^2)
             + lambda_smooth * mean_f           sum_i (|d_f+1,i - d_fi|^2 + s^2 |w_f+1,i - w_fi|^2)

s (`rotation_m`, 5 cm) weighs a radian of rotation like s metres of translation; the second sum runs over
consecutive training frames, every step, so each frame's correction also follows its neighbours' (the tracker's
error is a drift over frames, not a jitter: docs/experiments/garment_tracker_variants_2026-11-30/). Without it the
corrections moved the cloth's Gaussians more from frame to frame and the fit gained nothing
(docs/experiments/garment_track_refine_2026-11-30/). Novel poses (frame id -1) are placed as before.
"""

from __future__ import annotations

import torch
from torch import nn

from avatarctl.body.lbs import axis_angle_to_matrix


class TrackRefinement(nn.Module):
    """Rigid corrections w, d [F, N, 3] of the tracked nodes' placement per training frame (module docstring)."""

    def __init__(self, num_frames: int, num_nodes: int, lambda_size: float, lambda_smooth: float,
                 rotation_m: float):
        super().__init__()
        self.rotation = nn.Parameter(torch.zeros(num_frames, num_nodes, 3))  # [F, N, 3] w, axis-angle, radians
        self.translation = nn.Parameter(torch.zeros(num_frames, num_nodes, 3))  # [F, N, 3] d, metres
        self.lambda_size, self.lambda_smooth, self.rotation_m = lambda_size, lambda_smooth, rotation_m

    def forward(self, rotation: torch.Tensor, center: torch.Tensor, frames: torch.Tensor, nodes: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor]:
        """The tracked placement rotation [b, M, 3, 3], center [b, M, 3] of training frames `frames` [b] (indices)
        and nodes `nodes` [M] -> (R', c') of the module docstring."""
        w = self.rotation[frames][:, nodes].to(rotation.dtype)
        d = self.translation[frames][:, nodes].to(center.dtype)
        return axis_angle_to_matrix(w) @ rotation, center + d

    def penalty(self, frames: torch.Tensor, nodes: torch.Tensor) -> torch.Tensor:
        """L_refine of the module docstring for the batch's training frames `frames` [b] (indices, b >= 1) and the
        tracked nodes `nodes` [M]."""
        s2 = self.rotation_m ** 2

        def size(d: torch.Tensor, w: torch.Tensor) -> torch.Tensor:  # [k, M, 3] each -> [k]
            return (d ** 2).sum((-2, -1)) + s2 * (w ** 2).sum((-2, -1))

        d, w = self.translation[:, nodes], self.rotation[:, nodes]  # [F, M, 3]
        out = self.lambda_size * size(d[frames], w[frames]).mean()
        if self.lambda_smooth > 0 and d.shape[0] > 1:
            out = out + self.lambda_smooth * size(d[1:] - d[:-1], w[1:] - w[:-1]).mean()
        return out
