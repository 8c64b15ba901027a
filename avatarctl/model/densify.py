"""Density control of the Gaussian local fields under a fixed budget (`model.field = "gaussians"`).

3DGS grows and prunes its Gaussians by screen-space gradients; here every node owns exactly K Gaussians
(`GaussianConfig.per_node`), so memory is known in advance, and dead Gaussians are *relocated* instead (the rule of
3DGS as MCMC, Kheradmand et al. 2024, applied within each node so the node keeps its K): every
`GaussianConfig.relocate_every` steps, a Gaussian whose base opacity is below `min_opacity` takes the parameters of a
live Gaussian of its node, drawn with probability proportional to opacity; the n copies of a source (it included)
share its opacity as 1 - (1 - o)^(1/n), so the pair covers what the source covered; each copy is moved by one draw of
the source's own distribution. Their Adam moments restart at zero.

Deterministic: the draws come from a generator seeded by (seed, step), so a resumed fit relocates as a straight one.
"""

from __future__ import annotations

import torch

from avatarctl.model.gaussian_field import NodeGaussians
from avatarctl.splat.covariance import quaternion_to_matrix


@torch.no_grad()
def relocate_dead(fields: NodeGaussians, optimizer: torch.optim.Optimizer, min_opacity: float, seed: int,
                  step: int) -> int:
    """Relocate the dead Gaussians of every node (see the module docstring). -> how many moved."""
    opacity = torch.sigmoid(fields.opacity_logits)  # [N, K]
    dead = opacity < min_opacity
    live = ~dead
    rows = (dead.any(dim=1) & live.any(dim=1)).nonzero(as_tuple=True)[0]  # nodes with dead and live Gaussians
    if rows.numel() == 0:
        return 0
    gen = torch.Generator().manual_seed(int(seed) * 1_000_003 + int(step))
    K = opacity.shape[1]
    dev = opacity.device
    probs = (opacity * live)[rows].float().cpu()  # [n, K]
    draws = torch.multinomial(probs, K, replacement=True, generator=gen).to(dev)  # [n, K] sources per node
    d = dead[rows]
    rank = (torch.cumsum(d.long(), dim=1) - 1).clamp(min=0)
    src = torch.where(d, draws.gather(1, rank), torch.arange(K, device=dev).expand_as(d))  # [n, K]
    node = rows[:, None].expand_as(src)
    n_copies = torch.ones(rows.numel(), K, device=dev).scatter_add_(1, src, d.float())  # per source: 1 + copies
    share = n_copies.gather(1, src)  # [n, K] the count of each slot's source
    o_new = 1 - (1 - opacity[node, src]).clamp(max=1 - 1e-6) ** (1 / share)
    noise = torch.randn(rows.numel(), K, 3, generator=gen).to(dev)
    L = quaternion_to_matrix(fields.quats[node, src]) * fields.log_scales[node, src].exp()[..., None, :]
    moved = fields.means[node, src] + torch.where(d[..., None], (L @ noise[..., None]).squeeze(-1), 0.0)
    changed = d | (share > 1)  # the copies and their sources
    targets = {"means": moved, "log_scales": fields.log_scales[node, src], "quats": fields.quats[node, src],
               "opacity_logits": torch.logit(o_new.clamp(1e-6, 1 - 1e-6)), "sh": fields.sh[node, src],
               "features": fields.features[node, src]}
    if fields.shaded:
        targets["normals"] = fields.normals[node, src]
    for name, value in targets.items():
        p = getattr(fields, name)
        block = p[rows]
        mask = (d if name not in ("opacity_logits",) else changed).reshape(*d.shape, *([1] * (p.dim() - 2)))
        p[rows] = torch.where(mask, value, block)
        state = optimizer.state.get(p, {})
        for key in ("exp_avg", "exp_avg_sq"):
            if key in state:
                m = state[key][rows]
                state[key][rows] = torch.where(d.reshape(mask.shape), torch.zeros_like(m), m)
    return int(d.sum())
