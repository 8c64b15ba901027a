"""`CameraColour`: a colour transform per training camera, learned with the avatar (a deviation when on, issue 51;
`model.colour.enabled`: on in the `cpu` preset, off in the paper's settings).

Camera c sees the avatar's foreground through gain_c, offset_c per channel (`evaluate.colour.apply_colour`: the
formula and why 3 gains + 3 offsets rather than 3x3 + offset). The fit applies it to every rendered ray or crop of
camera c before the loss (fit/distributed.py), for both field kinds.

Gauge: the avatar's colour and the cameras' transforms are only known up to one common transform, so the log-gains
and the offsets are centred over the training cameras (their mean is identity): the avatar learns the training
cameras' mean colour, which is what a camera without a transform (a held-out view, a render) shows. With one
training camera the transform is identity. Regulariser: lambda_identity x the mean over cameras of
|log gain_c|^2 + |offset_c|^2 (centred values), towards identity.
"""

from __future__ import annotations

import torch
from torch import nn

from avatarctl.evaluate.colour import apply_colour


class CameraColour(nn.Module):
    """Per-channel gain and offset of each training camera (`names`, in the split's order)."""

    def __init__(self, names: tuple[str, ...] | list[str]):
        super().__init__()
        if not names:
            raise ValueError("model.colour needs the training cameras' names")
        self.names = tuple(str(n) for n in names)
        self.log_gain = nn.Parameter(torch.zeros(len(self.names), 3))  # [cams, 3] before centring
        self.offset = nn.Parameter(torch.zeros(len(self.names), 3))  # [cams, 3] before centring

    def transforms(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(gain [cams, 3], offset [cams, 3]) in the centred gauge (see the module docstring)."""
        lg = self.log_gain - self.log_gain.mean(0, keepdim=True)
        return lg.exp(), self.offset - self.offset.mean(0, keepdim=True)

    def index(self, views: list[str], device: torch.device | str = "cpu") -> torch.Tensor:
        """[len(views)] camera indices of training camera names."""
        try:
            return torch.tensor([self.names.index(v) for v in views], dtype=torch.long, device=device)
        except ValueError:
            raise ValueError(f"views {views} are not all training cameras {self.names}") from None

    def forward(self, rgb: torch.Tensor, alpha: torch.Tensor, background: torch.Tensor, cams: torch.Tensor
                ) -> torch.Tensor:
        """rgb [..., 3] composited over background [3], alpha [...], cams [...] camera index of each pixel ->
        [..., 3] as those cameras see it."""
        gain, offset = self.transforms()
        return apply_colour(rgb, alpha.to(rgb.dtype), background.to(rgb.dtype), gain[cams].to(rgb.dtype),
                            offset[cams].to(rgb.dtype))

    def penalty(self) -> torch.Tensor:
        """[] mean over cameras of |log gain|^2 + |offset|^2 (centred): the pull towards identity."""
        lg = self.log_gain - self.log_gain.mean(0, keepdim=True)
        off = self.offset - self.offset.mean(0, keepdim=True)
        return (lg ** 2 + off ** 2).sum(-1).mean()

    def of(self, view: str) -> tuple[list[float], list[float]] | None:
        """(gain [3], offset [3]) of training camera `view` as lists, or None for another camera (identity)."""
        if view not in self.names:
            return None
        gain, offset = self.transforms()
        i = self.names.index(view)
        return gain[i].tolist(), offset[i].tolist()
