"""The posed Gaussians of one frame as a browser splat renderer takes them (the viewer's page, the HTML player of
`export --format player`): centre, covariance, colour, opacity per Gaussian; `encode_splats` gives the compact wire
form the viewer sends to its page (and `decode_splats` its inverse).

What a browser splat renderer cannot show of our Gaussians: the view dependence. The model keeps spherical harmonics
of degree 1 in each node's local frame (model/gaussian_field.py); the page holds one RGB per Gaussian,
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


COV_SCALE = 1.0e4  # covariances are sent in cm^2 (metres^2 x 1e4): float16 keeps ~3 significant digits there


def encode_splats(frame: SplatFrame) -> tuple[dict, bytes]:
    """The wire form of a frame for the viewer's page (22 bytes a Gaussian instead of 40 in float32):
    (header, payload) with the payload, little-endian, in this order:
    - centres: uint16 [G, 3], quantised over the frame's box: c = lo + (hi - lo) * q / 65535 (header "lo", "hi";
      under 0.05 mm a step for a 2 m box);
    - covariances: float16 [G, 6], the upper triangles (xx, xy, xz, yy, yz, zz) times `COV_SCALE` (relative error
      under 2^-11 of each term);
    - colours and opacities: uint8 [G, 4], RGBA (the DC colour, opacity; 1/255 steps).
    """
    lo, hi = frame.bounds()
    span = np.maximum(hi - lo, 1e-9)
    q = np.clip(np.round((frame.centers - lo) / span * 65535.0), 0, 65535).astype("<u2")
    iu = np.triu_indices(3)
    cov = (frame.covariances[:, iu[0], iu[1]] * COV_SCALE).astype("<f2")  # [G, 6]
    rgba = np.clip(np.round(np.concatenate([frame.rgbs, frame.opacities], 1) * 255.0), 0, 255).astype(np.uint8)
    header = {"count": frame.count, "lo": [float(x) for x in lo], "hi": [float(x) for x in lo + span],
              "cov_scale": COV_SCALE}
    return header, q.tobytes() + cov.tobytes() + rgba.tobytes()


@dataclass(frozen=True)
class EncodedSplats:
    """A frame in its wire form (`encode_splats`: the header's fields, the payload), what the viewer caches, sends."""

    header: dict
    payload: bytes

    @property
    def count(self) -> int:
        return int(self.header["count"])

    @property
    def nbytes(self) -> int:
        return len(self.payload)

    @classmethod
    def of(cls, frame: SplatFrame) -> EncodedSplats:
        return cls(*encode_splats(frame))


def decode_splats(header: dict, payload: bytes) -> SplatFrame:
    """The inverse of `encode_splats` (what the page computes; for tests and the accuracy figures)."""
    g = int(header["count"])
    lo, hi = np.asarray(header["lo"], np.float32), np.asarray(header["hi"], np.float32)
    q = np.frombuffer(payload, "<u2", 3 * g, 0).reshape(g, 3)
    tri = np.frombuffer(payload, "<f2", 6 * g, 6 * g).reshape(g, 6).astype(np.float32) / header["cov_scale"]
    rgba = np.frombuffer(payload, np.uint8, 4 * g, 18 * g).reshape(g, 4).astype(np.float32) / 255.0
    cov = np.empty((g, 3, 3), np.float32)
    for k, (i, j) in enumerate(zip(*np.triu_indices(3))):
        cov[:, i, j] = cov[:, j, i] = tri[:, k]
    return SplatFrame(centers=lo + (hi - lo) * q.astype(np.float32) / 65535.0, covariances=cov, rgbs=rgba[:, :3],
                      opacities=rgba[:, 3:])
