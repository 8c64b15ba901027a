"""Parallel tiny MLPs, one per node, evaluated together with batched matrix products.

The paper implements the N local fields F_i and the N per-node cVAEs "with parallel tiny MLPs in the form of
group 1D convolution"; here each layer holds per-node weights [nodes, in, out] and runs `torch.baddbmm` on inputs
laid out [nodes, rows, in] (rows = packed samples for the fields, frames for the cVAEs). No Python loop over nodes.
"""

from __future__ import annotations

import math

import torch
from torch import nn


class BatchedLinear(nn.Module):
    """`nodes` independent linear layers: y[i] = x[i] @ W[i] + b[i].

    Initialised like `nn.Linear` (uniform in +-1/sqrt(in)) per node, times `init_scale`.
    """

    def __init__(self, nodes: int, in_dim: int, out_dim: int, bias: bool = True, init_scale: float = 1.0):
        super().__init__()
        bound = init_scale / math.sqrt(in_dim)
        self.weight = nn.Parameter(torch.empty(nodes, in_dim, out_dim).uniform_(-bound, bound))  # [nodes, in, out]
        self.bias = nn.Parameter(torch.empty(nodes, 1, out_dim).uniform_(-bound, bound)) if bias else None

    @property
    def nodes(self) -> int:
        return self.weight.shape[0]

    def forward(self, x: torch.Tensor, node_index: torch.Tensor | None = None) -> torch.Tensor:
        """[nodes, rows, in] -> [nodes, rows, out].

        With `node_index` [blocks] (long), x is [blocks, rows, in] and block k uses node `node_index[k]`'s weights.
        """
        W, b = self.weight, self.bias
        if node_index is not None:
            W = W[node_index]
            b = None if b is None else b[node_index]
        assert x.ndim == 3 and x.shape[0] == W.shape[0] and x.shape[2] == W.shape[1], \
            f"expected [nodes={W.shape[0]}, rows, in={W.shape[1]}], got {tuple(x.shape)}"
        if b is None:
            return torch.bmm(x, W)
        return torch.baddbmm(b, x, W)


class BatchedMLP(nn.Module):
    """`nodes` independent MLPs: Linear -> ReLU repeated, the last layer linear (no activation).

    `dims` = (in, hidden..., out). `last_init_scale` shrinks the initial output layer (e.g. to start the cVAE
    decoder near Delta n = 0).
    """

    def __init__(self, nodes: int, dims: tuple[int, ...] | list[int], last_init_scale: float = 1.0):
        super().__init__()
        assert len(dims) >= 2, f"dims needs (in, ..., out), got {dims}"
        n = len(dims) - 1
        self.layers = nn.ModuleList(
            BatchedLinear(nodes, dims[k], dims[k + 1], init_scale=last_init_scale if k == n - 1 else 1.0)
            for k in range(n))

    def forward(self, x: torch.Tensor, first_bias: torch.Tensor | None = None,
                node_index: torch.Tensor | None = None) -> torch.Tensor:
        """[nodes, rows, in] -> [nodes, rows, out] (or [blocks, rows, ...] with `node_index`, see BatchedLinear).

        `first_bias` [nodes, rows, hidden] is added to the first layer's pre-activation: a per-row conditioning
        term (W_e e) computed once per (frame, node) instead of concatenating e to every sample.
        """
        for k, layer in enumerate(self.layers):
            x = layer(x, node_index)
            if k == 0 and first_bias is not None:
                x = x + first_bias
            if k < len(self.layers) - 1:
                x = torch.relu(x)
        return x
