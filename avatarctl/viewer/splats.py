"""The posed Gaussians of one frame as a browser splat renderer takes them (viser's Gaussian-splat scene node, the
HTML player of `export --format player`): centre, covariance, colour, opacity per Gaussian.

What a browser splat renderer cannot show of our Gaussians: the view dependence. The model keeps spherical harmonics
of degree 1 in each node's local frame (model/gaussian_field.py); a splat node of viser holds one RGB per Gaussian,
so the colour sent is the degree-0 (DC) term, 0.5 + 0.28209479 sh_0: the colour averaged over viewing directions.
The exact, view-dependent image is the server render (`ViewerSession.render`, the viewer's "render" button).

Gaussians whose opacity is below 1/255 are left out (a byte of opacity rounds them to 0: the page would draw
nothing of them); `SplatFrame.dropped` counts them.

Units: metres, the capture's world frame; colours in [0, 1].
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from avatarctl.model.gaussian_field import PosedGaussians

MIN_OPACITY = 1.0 / 255.0


@dataclass(frozen=True)
class SplatFrame:
    """The Gaussians of one frame, world frame (G = those kept)."""

    centers: np.ndarray  # [G, 3] float32, metres
    covariances: np.ndarray  # [G, 3, 3] float32, metres^2
    rgbs: np.ndarray  # [G, 3] float32 in [0, 1], the DC colour (module docstring)
    opacities: np.ndarray  # [G, 1] float32 in [0, 1]
    dropped: int = 0  # Gaussians left out (opacity < 1/255)

    @property
    def count(self) -> int:
        return int(self.centers.shape[0])

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(min [3], max [3]) of the centres, metres."""
        if not self.count:
            return np.zeros(3, np.float32), np.zeros(3, np.float32)
        return self.centers.min(0), self.centers.max(0)


def splat_frame(posed: "PosedGaussians", slot: int, min_opacity: float = MIN_OPACITY) -> SplatFrame:
    """Frame `slot` of `posed` ([B, G, ...], `model.posed_gaussians`) as a `SplatFrame` (module docstring)."""
    import torch

    from avatarctl.model.gaussian_field import eval_sh

    with torch.no_grad():
        sh = posed.sh[slot, :, :1]  # [G, 1, 3] the DC band
        rgb = eval_sh(sh, sh.new_zeros(sh.shape[0], 3)).clamp(0.0, 1.0)
        opacity = posed.opacities[slot]
        keep = opacity >= min_opacity
        out = SplatFrame(centers=posed.means[slot][keep].float().cpu().numpy(),
                         covariances=posed.covars[slot][keep].float().cpu().numpy(),
                         rgbs=rgb[keep].float().cpu().numpy(),
                         opacities=opacity[keep, None].float().cpu().numpy(),
                         dropped=int((~keep).sum()))
    assert out.covariances.shape == (out.count, 3, 3), f"covariances {out.covariances.shape}"
    return out
