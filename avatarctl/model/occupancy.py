"""Empty-space skipping with a learned occupancy grid per node, in node-local coordinates (a named deviation,
docs/fit.md; `ModelConfig.occupancy`, an `OccupancyConfig`).

Most of the 64 samples of a ray through the union of node spheres land where the density is ~0 (air between the
limbs, in front of and behind the body). Each node i keeps a coarse grid O_i [res^3] over its support cube in
node-local coordinates (Eq. 4), so it moves and deforms with the node (pose, Delta n) like the field itself:

- a sample is *live* when any node in range (Eq. 6 weight > 0) has its cell marked occupied: O_i[cell] >= threshold
  (density, 1/metre) or O_i[cell] < 0 (never observed: occupied until seen);
- only live samples (and, in training, a random `explore` share of the others, so emptied cells can come back)
  are evaluated; the others get density 0;
- every evaluated sample updates the cells of all its pairs: O_i[cell] = max(decay * O_i[cell], density)
  (EMA-max as in nerfacc / InstantAvatar, but driven by the training samples themselves, not by extra queries).

Pure functions on the [nodes, res^3] buffer; the model owns the buffer and decides when to update.
"""

from __future__ import annotations

import torch

UNSEEN = -1.0  # initial value of every cell: not observed yet, treated as occupied


def cell_index(local: torch.Tensor, node: torch.Tensor, extent: float, res: int) -> torch.Tensor:
    """Flat cell index node * res^3 + (z * res + y) * res + x of each pair's local point (nearest cell).

    local [pairs, 3] node-local coordinates (units of `extent`, the cube half side), node [pairs] -> [pairs] long.
    """
    u = (local.detach() / (2.0 * extent) + 0.5).clamp(0.0, 1.0 - 1e-6)
    ijk = (u * res).long()  # [pairs, 3]
    return node * res ** 3 + (ijk[:, 2] * res + ijk[:, 1]) * res + ijk[:, 0]


def occupancy_estimate(occ: torch.Tensor, cells: torch.Tensor, point_idx: torch.Tensor,
                       num_points: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Per point: the largest cached density over its pairs' cells, and whether any of those cells is unseen.

    occ [nodes * res^3] (flat), cells [pairs], point_idx [pairs] -> density [num_points] (1/metre, 0 without
    pairs), unseen [num_points] bool.
    """
    o = occ[cells]
    density = torch.zeros(num_points, dtype=occ.dtype, device=occ.device).scatter_reduce_(
        0, point_idx, o.clamp_min(0.0), "amax", include_self=True)
    unseen = torch.zeros(num_points, dtype=torch.uint8, device=occ.device).index_add_(
        0, point_idx, (o < 0).to(torch.uint8)) > 0
    return density, unseen


def select_samples(density: torch.Tensor, unseen: torch.Tensor, threshold: float) -> torch.Tensor:
    """Which samples to evaluate. density, unseen [rays, samples] -> live [rays, samples] bool: the cached density
    is >= `threshold` or one of the sample's cells is unseen. (Early ray termination from the cached densities was
    tried and removed, docs/fit.md "Tried and removed".)"""
    return (density >= threshold) | unseen


def update_occupancy(occ: torch.Tensor, cells: torch.Tensor, density: torch.Tensor, decay: float) -> None:
    """In place: O[cell] = max(decay * O[cell], density) for every observed (cell, density) pair; unseen cells
    take the density. occ [nodes * res^3], cells [pairs], density [pairs] (>= 0, detached)."""
    if cells.numel() == 0:
        return
    seen = torch.unique(cells)
    old = occ[seen]
    occ[seen] = torch.where(old < 0, torch.zeros_like(old), old * decay)
    occ.scatter_reduce_(0, cells, density.to(occ.dtype), "amax", include_self=True)
