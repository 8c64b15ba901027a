"""The local radiance fields F_i, feature fusion (Eq. 5), the colour / density heads (Eq. 7), and the packing of
supplement Sec. C.2 that feeds only the valid node-sample pairs to the per-node MLPs.

Layout of a pair set (the sparse representation of the [nodes, samples] blending-weight matrix):
`point_idx [pairs]`, `node_idx [pairs]`, `frame_idx [pairs]`, `w [pairs]` (Eq. 6, all > 0).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from avatarctl.model.batched_mlp import BatchedLinear, BatchedMLP
from avatarctl.model.encoding import encoded_dim, positional_encoding


# ---- Eq. 5 -------------------------------------------------------------------------------------------------------
def fuse_features(features: torch.Tensor, w: torch.Tensor, point_idx: torch.Tensor,
                  num_points: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Eq. 5: f = sum_i w_i F_i(p_i; e_i) / sum_i w_i, over the pairs of each point.

    features [pairs, F], w [pairs], point_idx [pairs] -> f [points, F], wsum [points]. Points without any pair
    (wsum = 0) get f = 0; callers give them zero density.
    """
    F = features.shape[-1]
    src = w[:, None] * features  # float32 under bf16 autocast (w is float32): the sum accumulates in float32
    num = src.new_zeros(num_points, F).index_add(0, point_idx, src)
    wsum = w.new_zeros(num_points).index_add(0, point_idx, w)
    return num / wsum.clamp_min(1e-30)[:, None], wsum


def fuse_features_dense(features: torch.Tensor, w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Eq. 5 on the dense layout: features [N, points, F], w [N, points] -> f [points, F], wsum [points]."""
    wsum = w.sum(0)
    return (w[..., None] * features).sum(0) / wsum.clamp_min(1e-30)[:, None], wsum


# ---- supplement C.2 packing --------------------------------------------------------------------------------------
@dataclass
class Packing:
    """Where each valid pair sits in the packed [N, S', C] tensor, S' = max_i S_i."""

    order: torch.Tensor  # [pairs] permutation sorting pairs by node
    node: torch.Tensor  # [pairs] node of each sorted pair
    slot: torch.Tensor  # [pairs] row of each sorted pair inside its node's block
    counts: torch.Tensor  # [N] S_i, valid pairs per node
    width: int  # S' = max_i S_i

    @staticmethod
    def build(node_idx: torch.Tensor, num_nodes: int) -> "Packing":
        order = torch.argsort(node_idx, stable=True)
        node = node_idx[order]
        counts = torch.bincount(node_idx, minlength=num_nodes)
        starts = torch.cumsum(counts, 0) - counts
        slot = torch.arange(node.shape[0], device=node.device) - starts[node]
        width = int(counts.max()) if node.numel() else 0
        return Packing(order=order, node=node, slot=slot, counts=counts, width=width)

    def pack(self, values: torch.Tensor, num_nodes: int) -> torch.Tensor:
        """[pairs, C] (original pair order) -> [N, S', C], zero padded."""
        out = values.new_zeros(num_nodes, self.width, values.shape[-1])
        return out.index_put((self.node, self.slot), values[self.order])

    def pack_index(self, index: torch.Tensor, num_nodes: int, fill: int) -> torch.Tensor:
        """[pairs] long (original pair order) -> [N, S'] long, padding = `fill`."""
        out = torch.full((num_nodes, self.width), fill, dtype=index.dtype, device=index.device)
        return out.index_put((self.node, self.slot), index[self.order])

    def unpack(self, packed: torch.Tensor) -> torch.Tensor:
        """[N, S', C] -> [pairs, C] in the sorted pair order (`order`)."""
        return packed[self.node, self.slot]


@dataclass
class BlockPacking:
    """Pairs sorted by node, each node's run cut into blocks of `block` rows: [blocks, block, C], zero padded.

    The per-node MLPs then run with per-block weights (`BatchedMLP(..., node_index=block_node)`); padding is below
    `block` rows per node instead of max_i S_i - S_i (see `ModelConfig.pack_block`).
    """

    order: torch.Tensor  # [pairs] permutation sorting pairs by node
    pos: torch.Tensor  # [pairs] row of each sorted pair in the flattened [blocks * block] layout
    block_node: torch.Tensor  # [blocks] node of each block
    block: int

    @staticmethod
    def build(node_idx: torch.Tensor, num_nodes: int, block: int) -> "BlockPacking":
        order = torch.argsort(node_idx, stable=True)
        node = node_idx[order]
        counts = torch.bincount(node_idx, minlength=num_nodes)
        nblk = (counts + block - 1) // block  # [N]
        first_block = torch.cumsum(nblk, 0) - nblk
        rank = torch.arange(node.shape[0], device=node.device) - (torch.cumsum(counts, 0) - counts)[node]
        pos = first_block[node] * block + rank
        block_node = torch.repeat_interleave(torch.arange(num_nodes, device=node.device), nblk)
        return BlockPacking(order=order, pos=pos, block_node=block_node, block=block)

    @property
    def num_blocks(self) -> int:
        return int(self.block_node.shape[0])

    def pack(self, values_sorted: torch.Tensor) -> torch.Tensor:
        """[pairs, C] in sorted order -> [blocks, block, C], zero padded."""
        out = values_sorted.new_zeros(self.num_blocks * self.block, values_sorted.shape[-1])
        return out.index_copy(0, self.pos, values_sorted).reshape(self.num_blocks, self.block, -1)

    def unpack(self, packed: torch.Tensor) -> torch.Tensor:
        """[blocks, block, C] -> [pairs, C] in sorted order."""
        return packed.reshape(-1, packed.shape[-1])[self.pos]


# ---- networks ----------------------------------------------------------------------------------------------------
class CoordinateEncoding(nn.Module):
    """gamma(p) of the MLP fields' input coordinates (m = pe_coords)."""

    def __init__(self, pe_coords: int):
        super().__init__()
        self.pe_coords = pe_coords

    def encode(self, coords: torch.Tensor) -> torch.Tensor:
        return positional_encoding(coords, self.pe_coords)

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        # checkpoints written before issue 30 carry the coarse-to-fine level of gamma(p) (removed, docs/fit.md "Tried
        # and removed"); a fully open level is the plain encoding
        level = state_dict.pop(prefix + "pe_level", None)
        if level is not None and float(level) < self.pe_coords:
            raise ValueError(f"this checkpoint's gamma(p) is not fully open ({float(level):g} of {self.pe_coords} "
                             f"bands): coarse-to-fine encoding was removed in issue 30; use avatarctl at commit "
                             f"0081142")
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)


class NodeFields(CoordinateEncoding):
    """The N local radiance networks F_i(p_i; e_i) (Sec. 3), run in parallel over a `nodes` dimension.

    Input: gamma(p_i) (m = pe_coords) and the detail embedding e_i. e_i enters the first layer as a per-(frame, node)
    bias W_e e_i (identical to concatenating e_i to every sample, computed once per frame and node).
    """

    def __init__(self, num_nodes: int, pe_coords: int, embed_dim: int, width: int, depth: int, feature_dim: int):
        super().__init__(pe_coords)
        self.in_dim = encoded_dim(3, pe_coords)
        self.mlp = BatchedMLP(num_nodes, [self.in_dim] + [width] * depth + [feature_dim])
        self.embed = BatchedLinear(num_nodes, embed_dim, width, bias=False)

    def embed_bias(self, embed: torch.Tensor) -> torch.Tensor:
        """[frames, N, E] -> [frames, N, width], the first-layer contribution of e_i."""
        return self.embed(embed.transpose(0, 1)).transpose(0, 1)

    def forward(self, coords: torch.Tensor, bias: torch.Tensor, node_index: torch.Tensor | None = None) -> torch.Tensor:
        """coords [N, rows, 3] local coordinates (already scaled), bias [N, rows, width] -> features [N, rows, F].

        With `node_index` [blocks] the leading dimension is blocks of `BlockPacking` (block k = node node_index[k]).
        """
        return self.mlp(self.encode(coords), first_bias=bias, node_index=node_index)


class CanonicalField(CoordinateEncoding):
    """One canonical radiance network for the "lbs_baseline" variant (Animatable-NeRF-style, pose-only):
    gamma(x_c) of a canonical point (metres) -> feature [points, F]."""

    def __init__(self, pe_coords: int, width: int, depth: int, feature_dim: int):
        super().__init__(pe_coords)
        self.mlp = BatchedMLP(1, [encoded_dim(3, pe_coords)] + [width] * depth + [feature_dim])

    def forward(self, x_canonical: torch.Tensor) -> torch.Tensor:
        return self.mlp(self.encode(x_canonical)[None])[0]


class RadianceHeads(nn.Module):
    """Eq. 7: Density(p) = H(f), Colour(p) = G(f, v).

    H: Linear(F, head_width) -> ReLU -> Linear(1) -> softplus (1/metre; the paper does not name the activation: our
    choice. A scaled / shifted softplus was tried and removed, docs/fit.md "Tried and removed").
    G: Linear([f, gamma(v)], head_width) -> ReLU -> Linear(head_width // 2) -> ReLU -> Linear(3) -> sigmoid.
    v is the unit viewing direction in world space (m = pe_views).
    """

    def __init__(self, feature_dim: int, width: int, pe_views: int):
        super().__init__()
        self.pe_views = pe_views
        self.density_net = nn.Sequential(nn.Linear(feature_dim, width), nn.ReLU(), nn.Linear(width, 1))
        self.color_net = nn.Sequential(nn.Linear(feature_dim + encoded_dim(3, pe_views), width), nn.ReLU(),
                                       nn.Linear(width, width // 2), nn.ReLU(), nn.Linear(width // 2, 3))

    def density(self, f: torch.Tensor) -> torch.Tensor:
        """H(f): [points, F] -> [points] >= 0 (1/metre): softplus(net(f))."""
        return nn.functional.softplus(self.density_net(f)[..., 0])

    def color(self, f: torch.Tensor, view_dirs: torch.Tensor) -> torch.Tensor:
        """G(f, v): [points, F], [points, 3] -> [points, 3] in (0, 1)."""
        return torch.sigmoid(self.color_net(torch.cat([f, positional_encoding(view_dirs, self.pe_views)], -1)))
