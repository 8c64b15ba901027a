"""Per-node learned feature grids: the `grid` backend of the local fields F_i (a named deviation, docs/fit.md).

The paper's F_i is a small MLP per node (`field.NodeFields`, kept as `ModelConfig.field = "mlp"`, the `paper`
preset). Here each node i owns a multi-resolution stack of dense feature grids over its support cube in node-local
coordinates (Eq. 4), read by trilinear interpolation, and

    F_i(p_i; e_i) = W_g [g_i^1(p_i), ..., g_i^L(p_i)] + B_i e_i                                   (grid backend)

with W_g one linear decoder shared by all nodes and B_i a per-node projection of the dynamic detail embedding e_i
(the same per-(frame, node) term W_e e_i that enters the MLP's first layer). F_i is affine in the grid features, so
the Eq. 5 fusion f = sum_i w_i F_i / sum_i w_i equals W_g (sum_i w_i g_i / sum_i w_i) + sum_i w_i B_i e_i / sum_i
w_i: the model fuses the raw grid features and the embedding terms over the pairs of each point and applies W_g
once per point. The non-linearity is in the heads H and G (Eq. 7), as in Instant-NGP / InstantAvatar, whose small
decoder reads a hash grid.

Storage: level l is one parameter [nodes * D_l^3, C] (flat, so one gather serves every node); a pair's cell index
is node * D_l^3 + (z * D_l + y) * D_l + x. Grid coordinates: u = (p_i / extent + 1) / 2 in [0, 1]^3 where
`extent` is the support radius in the units of p_i, so the cube [-extent, extent]^3 holds the whole support ball.
Pure PyTorch (gathers + index-add in the backward); runs on CPU and GPU.
"""

from __future__ import annotations

import torch
from torch import nn

from avatarctl.model.batched_mlp import BatchedLinear

# the 8 corners of a cell as (dx, dy, dz) offsets
_CORNERS = torch.tensor([[(c >> 0) & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)], dtype=torch.long)


def trilinear_lookup(table: torch.Tensor, res: int, node: torch.Tensor, u: torch.Tensor,
                     reference: bool = False) -> torch.Tensor:
    """Trilinear interpolation in per-node dense grids.

    table [nodes * res^3, C] (node-major, then z, y, x), node [pairs] long, u [pairs, 3] in [0, 1] (x, y, z;
    clamped) -> [pairs, C]. Grid vertices sit at u = k / (res - 1). `reference=True` runs the plain-autograd twin
    of the weighted gather (`embedding` + sum) instead of `_GatherBlend`; a test keeps the two equal.
    """
    assert u.ndim == 2 and u.shape[1] == 3 and node.shape == u.shape[:1], \
        f"u: expected [pairs, 3] with node [pairs], got {tuple(u.shape)} and {tuple(node.shape)}"
    x = u.clamp(0.0, 1.0) * (res - 1)  # [pairs, 3]
    i0 = x.detach().floor().long().clamp_(0, res - 2)  # [pairs, 3]
    frac = x - i0.to(x.dtype)  # [pairs, 3], differentiable in u
    corners = _CORNERS.to(u.device)  # [8, 3]
    base = node * res ** 3 + (i0[:, 2] * res + i0[:, 1]) * res + i0[:, 0]  # [pairs]
    idx = base[:, None] + ((corners[:, 2] * res + corners[:, 1]) * res + corners[:, 0])[None]  # [pairs, 8]
    wx, wy, wz = (torch.stack([1.0 - frac[:, k], frac[:, k]], -1) for k in range(3))  # [pairs, 2] each
    wc = (wz[:, :, None, None] * wy[:, None, :, None] * wx[:, None, None, :]).reshape(-1, 8)  # corner c = x + 2y + 4z
    if reference:
        return (nn.functional.embedding(idx, table) * wc[..., None].to(table.dtype)).sum(1)
    return _GatherBlend.apply(table, idx, wc.to(table.dtype))


class _GatherBlend(torch.autograd.Function):
    """out[p] = sum_k wc[p, k] table[idx[p, k]]: a weighted gather whose backward scatters into the table with one
    `index_add_` (3-4x faster on CPU than the backward of `embedding` / advanced indexing, measured at 58k pairs).
    table [rows, C], idx [pairs, K] long, wc [pairs, K] -> [pairs, C]; gradients for table and wc."""

    @staticmethod
    def forward(ctx, table: torch.Tensor, idx: torch.Tensor, wc: torch.Tensor) -> torch.Tensor:
        vals = table[idx]  # [pairs, K, C], kept for the wc gradient
        ctx.table_shape = table.shape
        ctx.save_for_backward(vals, idx, wc)
        return torch.bmm(wc[:, None, :], vals)[:, 0]

    @staticmethod
    def backward(ctx, grad_out: torch.Tensor):
        vals, idx, wc = ctx.saved_tensors
        grad_table = grad_wc = None
        if ctx.needs_input_grad[0]:
            contrib = (wc[..., None] * grad_out[:, None, :]).reshape(-1, vals.shape[-1])  # [pairs * K, C]
            grad_table = vals.new_zeros(ctx.table_shape).index_add_(0, idx.reshape(-1), contrib)
        if ctx.needs_input_grad[2]:
            grad_wc = torch.bmm(vals, grad_out[:, :, None])[..., 0]
        return grad_table, None, grad_wc


class NodeGridFields(nn.Module):
    """The N local fields F_i as per-node multi-resolution feature grids (see the module docstring).

    `levels`: grid resolutions D_l (vertices per side); `channels`: C features per level; `extent`: half the cube
    side in local-coordinate units (the support radius). `init_std`: initial grid values ~ N(0, init_std^2).
    """

    def __init__(self, num_nodes: int, levels: tuple[int, ...], channels: int, embed_dim: int, feature_dim: int,
                 extent: float, init_std: float = 1e-2):
        super().__init__()
        assert all(d >= 2 for d in levels), f"grid levels need >= 2 vertices per side, got {levels}"
        self.num_nodes, self.levels, self.channels, self.extent = num_nodes, tuple(levels), channels, float(extent)
        self.tables = nn.ParameterList(
            nn.Parameter(init_std * torch.randn(num_nodes * d ** 3, channels)) for d in self.levels)
        self.decoder = nn.Linear(len(self.levels) * channels, feature_dim)  # W_g, shared by all nodes
        self.embed = BatchedLinear(num_nodes, embed_dim, feature_dim, bias=False)  # B_i

    @property
    def grid_dim(self) -> int:
        return len(self.levels) * self.channels

    def embed_bias(self, embed: torch.Tensor) -> torch.Tensor:
        """[frames, N, E] -> [frames, N, F]: B_i e_i for every frame and node."""
        return self.embed(embed.transpose(0, 1)).transpose(0, 1)

    def grid_features(self, local: torch.Tensor, node: torch.Tensor) -> torch.Tensor:
        """local [pairs, 3] node-local coordinates (Eq. 4 units), node [pairs] long -> [pairs, L * C]."""
        u = local / (2.0 * self.extent) + 0.5
        return torch.cat([trilinear_lookup(t, d, node, u) for t, d in zip(self.tables, self.levels)], -1)

    def decode(self, fused_grid: torch.Tensor, fused_embed: torch.Tensor) -> torch.Tensor:
        """Eq. 5 for the affine F_i: W_g (fused grid features) + (fused B_i e_i). [points, L*C], [points, F]."""
        return self.decoder(fused_grid) + fused_embed

    def grid_parameters(self) -> list[nn.Parameter]:
        """The grid tables (trained with their own learning rate, `FitConfig.lr_grid`)."""
        return list(self.tables)
