"""Sinusoidal positional encoding of the supplement (Sec. C.1):

    gamma(x) = (x, sin(x), cos(x), sin(2x), cos(2x), ..., sin(2^(m-1) x), cos(2^(m-1) x))

applied per component; m = 6 for coordinates, 4 for view directions, 12 for the normalised time stamp t/T.
The input itself is included, so a d-dimensional input encodes to d * (1 + 2m) values.
"""

from __future__ import annotations

import torch


def encoded_dim(dim: int, m: int) -> int:
    """Width of gamma(x) for a `dim`-dimensional x and m frequencies."""
    return dim * (1 + 2 * m)


def positional_encoding(x: torch.Tensor, m: int) -> torch.Tensor:
    """[..., d] -> [..., d * (1 + 2m)], laid out as (x, sin(2^0 x), cos(2^0 x), sin(2^1 x), ...), each block [d]."""
    if m == 0:
        return x
    freqs = 2.0 ** torch.arange(m, dtype=x.dtype, device=x.device)  # [m]
    xf = x[..., None, :] * freqs[:, None]  # [..., m, d]
    sc = torch.stack([torch.sin(xf), torch.cos(xf)], dim=-2)  # [..., m, 2, d]
    return torch.cat([x, sc.flatten(-3)], dim=-1)
