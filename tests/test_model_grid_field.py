"""The `grid` local-field backend (model/grid_field.py): trilinear lookup against torch's grid_sample, per-node
tables, and the affine F_i that makes fusing before decoding equal to Eq. 5."""

from __future__ import annotations

import torch

from avatarctl.model.grid_field import NodeGridFields, trilinear_lookup


def test_trilinear_lookup_matches_grid_sample_per_node():
    g = torch.Generator().manual_seed(0)
    nodes, res, C, P = 3, 5, 4, 200
    table = torch.randn(nodes * res ** 3, C, generator=g)
    node = torch.randint(0, nodes, (P,), generator=g)
    u = torch.rand(P, 3, generator=g)
    got = trilinear_lookup(table, res, node, u)
    vol = table.reshape(nodes, res, res, res, C).permute(0, 4, 1, 2, 3)  # [nodes, C, z, y, x]
    for n in range(nodes):
        sel = node == n
        grid = (u[sel] * 2 - 1)[None, None, None]  # [1, 1, 1, P_n, 3] (x, y, z)
        ref = torch.nn.functional.grid_sample(vol[n:n + 1], grid, mode="bilinear", align_corners=True)
        assert torch.allclose(got[sel], ref[0, :, 0, 0].T, atol=1e-5)


def test_lookup_at_grid_vertices_returns_the_stored_values_and_clamps_outside():
    res, C = 4, 2
    table = torch.arange(2 * res ** 3 * C, dtype=torch.float32).reshape(-1, C)
    node = torch.tensor([1, 1, 0])
    u = torch.tensor([[1 / 3, 2 / 3, 1.0], [0.0, 0.0, 0.0], [-0.5, 1.5, 0.0]])
    got = trilinear_lookup(table, res, node, u)
    expect = torch.stack([table[1 * 64 + (3 * 4 + 2) * 4 + 1], table[64], table[(0 * 4 + 3) * 4 + 0]])
    assert torch.allclose(got, expect, atol=1e-4)


def test_gradients_reach_only_the_corners_touched():
    f = NodeGridFields(num_nodes=4, levels=(4,), channels=3, embed_dim=5, feature_dim=6, extent=1.0)
    local = torch.tensor([[0.1, -0.2, 0.3]])
    f.grid_features(local, torch.tensor([2])).sum().backward()
    grad = f.tables[0].grad.abs().sum(-1).reshape(4, -1)
    assert int((grad[2] > 0).sum()) == 8 and float(grad[[0, 1, 3]].sum()) == 0.0


def test_affine_field_fuse_then_decode_equals_eq5_on_per_node_features():
    """W_g (sum w g_i / sum w) + sum w B_i e_i / sum w == sum_i w_i F_i / sum_i w_i with F_i = W_g g_i + B_i e_i."""
    torch.manual_seed(0)
    f = NodeGridFields(num_nodes=5, levels=(3, 6), channels=2, embed_dim=4, feature_dim=7, extent=2.0)
    node = torch.tensor([0, 3, 4])
    local = torch.randn(3, 3)
    w = torch.tensor([0.2, 0.5, 0.3])
    e = torch.randn(1, 5, 4)
    per_node = f.decoder(f.grid_features(local, node)) + f.embed_bias(e)[0, node]  # F_i of each pair
    eq5 = (w[:, None] * per_node).sum(0) / w.sum()
    fused = f.decode((w[:, None] * f.grid_features(local, node)).sum(0, keepdim=True) / w.sum(),
                     (w[:, None] * f.embed_bias(e)[0, node]).sum(0, keepdim=True) / w.sum())
    assert torch.allclose(fused[0], eq5, atol=1e-6)


def test_gather_blend_matches_its_plain_autograd_twin_values_and_gradients():
    g = torch.Generator().manual_seed(3)
    res, C, P = 6, 3, 500
    table = torch.randn(4 * res ** 3, C, generator=g)
    node = torch.randint(0, 4, (P,), generator=g)
    u0 = torch.rand(P, 3, generator=g)
    upstream = torch.randn(P, C, generator=g)
    outs = []
    for reference in (False, True):
        t = table.clone().requires_grad_(True)
        u = u0.clone().requires_grad_(True)
        out = trilinear_lookup(t, res, node, u, reference=reference)
        (out * upstream).sum().backward()
        outs.append((out.detach(), t.grad, u.grad))
    for a, b in zip(*outs):
        assert torch.allclose(a, b, atol=1e-5), (a - b).abs().max()
    assert float(outs[0][2].abs().sum()) > 0  # the position gradient (it moves Delta n) is not dropped
