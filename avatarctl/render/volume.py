"""Volume rendering (NeRF quadrature) over a known background colour. Knows nothing about the model.

Steps: `uniform_samples` places `n` samples per ray between near and far; a field gives colour and density at the
samples (`march` takes it as a callback); `composite` integrates them:

    delta_k = t_{k+1} - t_k (the last sample reuses the previous spacing),
    alpha_k = 1 - exp(-sigma_k delta_k),   T_k = exp(-sum_{l<k} sigma_l delta_l),   w_k = T_k alpha_k,
    C = sum_k w_k c_k + (1 - sum_k w_k) * background.

Units: t and delta in metres along unit-length directions, sigma in 1/metre, colours in [0, 1].
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch


@dataclass
class Composited:
    rgb: torch.Tensor  # [rays, 3] composited over the background
    alpha: torch.Tensor  # [rays] accumulated opacity sum_k w_k
    depth: torch.Tensor  # [rays] expected termination distance given the ray terminates; 0 where alpha = 0
    weights: torch.Tensor  # [rays, samples] w_k


def uniform_samples(near: torch.Tensor, far: torch.Tensor, n: int, jitter: bool = False,
                    generator: torch.Generator | None = None) -> torch.Tensor:
    """[rays] near, [rays] far -> t [rays, n]: one sample per equal bin, at the bin centre (jitter=False) or
    uniformly inside the bin (stratified, jitter=True, drawn from `generator`). Sorted along the ray."""
    assert near.shape == far.shape and near.ndim == 1, f"near {tuple(near.shape)}, far {tuple(far.shape)}"
    if jitter:
        dev = generator.device if generator is not None else near.device
        u = torch.rand(near.shape[0], n, generator=generator, device=dev, dtype=near.dtype).to(near.device)
    else:
        u = torch.full((near.shape[0], n), 0.5, dtype=near.dtype, device=near.device)
    frac = (torch.arange(n, dtype=near.dtype, device=near.device) + u) / n  # [rays, n]
    return near[:, None] + (far - near)[:, None] * frac


def sample_deltas(t: torch.Tensor) -> torch.Tensor:
    """[rays, samples] sorted t -> [rays, samples] segment lengths; the last reuses the previous spacing, so bin
    centres of n equal bins over [near, far] give lengths summing exactly to far - near."""
    d = t[:, 1:] - t[:, :-1]
    return torch.cat([d, d[:, -1:]], dim=-1)


def composite(rgb: torch.Tensor, sigma: torch.Tensor, t: torch.Tensor,
              background: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Alpha compositing along rays (NeRF Eq. 3 quadrature).

    rgb [rays, samples, 3], sigma [rays, samples] (>= 0, 1/metre), t [rays, samples] (sorted, metres),
    background [3] -> (rgb [rays, 3], alpha [rays], depth [rays], weights [rays, samples]).
    """
    R, S = sigma.shape
    assert rgb.shape == (R, S, 3) and t.shape == (R, S), \
        f"rgb {tuple(rgb.shape)}, sigma {tuple(sigma.shape)}, t {tuple(t.shape)}"
    if S == 0 or R == 0:
        z = sigma.new_zeros(R)
        return background.to(rgb.dtype).expand(R, 3).clone(), z, z, sigma.new_zeros(R, S)
    tau = sigma * sample_deltas(t)  # [rays, samples] optical depth of each segment
    alpha_k = 1.0 - torch.exp(-tau)
    trans = torch.exp(-(torch.cumsum(tau, dim=-1) - tau))  # exclusive cumulative sum
    weights = trans * alpha_k
    alpha = weights.sum(-1)
    out = (weights[..., None] * rgb).sum(-2) + (1.0 - alpha)[:, None] * background.to(rgb.dtype)
    depth = torch.where(alpha > 0, (weights * t).sum(-1) / alpha.clamp_min(1e-10), torch.zeros_like(alpha))
    return out, alpha, depth, weights


FieldFn = Callable[[torch.Tensor, torch.Tensor], tuple[torch.Tensor, torch.Tensor]]
"""(points [rays, samples, 3], dirs [rays, samples, 3]) -> (rgb [rays, samples, 3], sigma [rays, samples])."""


def march(field: FieldFn, origins: torch.Tensor, dirs: torch.Tensor, near: torch.Tensor, far: torch.Tensor,
          n: int, background: torch.Tensor, jitter: bool = False,
          generator: torch.Generator | None = None) -> Composited:
    """Sample `n` points per ray uniformly in [near, far], query `field`, composite over `background`.

    origins, dirs [rays, 3] world (dirs unit), near/far [rays] metres.
    """
    t = uniform_samples(near, far, n, jitter, generator)  # [rays, n]
    pts = origins[:, None, :] + t[..., None] * dirs[:, None, :]  # [rays, n, 3]
    rgb, sigma = field(pts, dirs[:, None, :].expand_as(pts))
    c, a, d, w = composite(rgb, sigma, t, background)
    return Composited(rgb=c, alpha=a, depth=d, weights=w)
