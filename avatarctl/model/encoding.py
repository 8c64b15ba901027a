"""Sinusoidal positional encoding of the supplement (Sec. C.1):

    gamma(x) = (x, sin(x), cos(x), sin(2x), cos(2x), ..., sin(2^(m-1) x), cos(2^(m-1) x))

applied per component; m = 6 for coordinates, 4 for view directions, 12 for the normalised time stamp t/T.
The input itself is included, so a d-dimensional input encodes to d * (1 + 2m) values.

Coarse-to-fine (a deviation, `ModelConfig.pe_anneal_steps`): band k's sin / cos may be scaled by a weight w_k(a)
that opens it as the level a passes k (the window of BARF, Lin et al. 2021):
w_k = (1 - cos(pi clamp(a - k, 0, 1))) / 2. At a = m every weight is 1 and the encoding is exactly gamma(x).
"""

from __future__ import annotations

import torch


def encoded_dim(dim: int, m: int) -> int:
    """Width of gamma(x) for a `dim`-dimensional x and m frequencies."""
    return dim * (1 + 2 * m)


def band_weights(m: int, level: float) -> torch.Tensor:
    """The coarse-to-fine window: [m] weights of the frequency bands at `level` a (0 = only x, m = all bands)."""
    k = torch.arange(m, dtype=torch.float32)
    return 0.5 * (1.0 - torch.cos(torch.pi * (float(level) - k).clamp(0.0, 1.0)))


def positional_encoding(x: torch.Tensor, m: int, weights: torch.Tensor | None = None) -> torch.Tensor:
    """[..., d] -> [..., d * (1 + 2m)], laid out as (x, sin(2^0 x), cos(2^0 x), sin(2^1 x), ...), each block [d].
    `weights` [m] (optional, `band_weights`): band k's sin and cos are scaled by weights[k]."""
    if m == 0:
        return x
    freqs = 2.0 ** torch.arange(m, dtype=x.dtype, device=x.device)  # [m]
    xf = x[..., None, :] * freqs[:, None]  # [..., m, d]
    sc = torch.stack([torch.sin(xf), torch.cos(xf)], dim=-2)  # [..., m, 2, d]
    if weights is not None:
        sc = sc * weights.to(sc)[:, None, None]
    return torch.cat([x, sc.flatten(-3)], dim=-1)
