"""Equation-level tests of the SLRF model parts (Eq. 1, 3, 4, 5, 6, 7, 8; PE; FPS; batched MLPs; config)."""

from __future__ import annotations

import math

import pytest
import torch

from avatarctl.body.lbs import axis_angle_to_matrix, make_transform
from avatarctl.model.batched_mlp import BatchedLinear, BatchedMLP
from avatarctl.fit.config import preset
from avatarctl.model.config import ModelConfig
from avatarctl.model.deformer import (blending_weights, candidate_pairs, farthest_point_sampling,
                                      kinematic_hop_distance, local_coordinates, local_coordinates_centered,
                                      node_pose_attention, node_pose_condition, node_transforms, pose_attention_map,
                                      posed_node_centers, ray_sphere_bounds, support_radius)
from avatarctl.model.encoding import encoded_dim, positional_encoding
from avatarctl.model.field import Packing, RadianceHeads, fuse_features, fuse_features_dense
from avatarctl.body.toy import sphere_template


def _rot_z(angle: float) -> torch.Tensor:
    return axis_angle_to_matrix(torch.tensor([0.0, 0.0, angle]))


# ---- Eq. 1 / 3 / 4 -----------------------------------------------------------------------------------------------
def test_eq1_node_transform_is_weighted_sum_of_joint_transforms():
    M0 = make_transform(torch.eye(3), torch.tensor([1.0, 0.0, 0.0]))
    M1 = make_transform(_rot_z(math.pi / 2), torch.tensor([0.0, 2.0, 0.0]))
    M = torch.stack([M0, M1])[None]  # [1, 2, 4, 4]
    w = torch.tensor([[1.0, 0.0], [0.25, 0.75]])
    T = node_transforms(w, M)
    assert T.shape == (1, 2, 4, 4)
    assert torch.allclose(T[0, 0], M0)
    assert torch.allclose(T[0, 1], 0.25 * M0 + 0.75 * M1)


def test_eq3_posed_node_with_residual():
    T = make_transform(_rot_z(math.pi / 2), torch.tensor([0.0, 0.0, 1.0]))[None, None]  # [1, 1, 4, 4]
    n_bar = torch.tensor([[1.0, 0.0, 0.0]])
    delta = torch.tensor([[[0.0, 0.5, 0.0]]])
    n = posed_node_centers(T, n_bar, delta)
    # Rz(90) (1, 0.5, 0) = (-0.5, 1, 0), + (0, 0, 1)
    assert torch.allclose(n[0, 0], torch.tensor([-0.5, 1.0, 1.0]), atol=1e-6)
    # Eq. 2 (no residual)
    assert torch.allclose(posed_node_centers(T, n_bar, torch.zeros_like(delta))[0, 0],
                          torch.tensor([0.0, 1.0, 1.0]), atol=1e-6)


def test_eq4_local_coordinates_hand_example_and_centered_form():
    T = make_transform(_rot_z(math.pi / 2), torch.tensor([0.0, 0.0, 1.0]))
    n_bar = torch.tensor([1.0, 0.0, 0.0])
    delta = torch.tensor([0.0, 0.5, 0.0])
    p = torch.tensor([-0.5, 1.2, 1.0])  # = T (n_bar + delta + (0.2, 0, 0))
    p_i = local_coordinates(p, T, n_bar, delta)
    assert torch.allclose(p_i, torch.tensor([0.2, 0.0, 0.0]), atol=1e-6)
    # the centered form used by the model agrees, also for a non-rigid blended transform
    g = torch.Generator().manual_seed(0)
    A = torch.eye(3) + 0.2 * torch.randn(3, 3, generator=g)
    Tn = make_transform(A, torch.randn(3, generator=g))
    pts = torch.randn(5, 3, generator=g)
    center = posed_node_centers(Tn[None, None], n_bar[None], delta[None, None])[0, 0]
    ref = local_coordinates(pts, Tn, n_bar, delta)
    got = local_coordinates_centered(pts, torch.linalg.inv(A), center)
    assert torch.allclose(got, ref, atol=1e-5)


# ---- Eq. 6 -------------------------------------------------------------------------------------------------------
def test_eq6_blending_weight_values_and_truncation_radius():
    sigma, eps = 0.05, 0.001
    r = support_radius(sigma, eps)
    assert r == pytest.approx(0.18585, abs=1e-4)
    assert ModelConfig().support_radius == pytest.approx(r)
    d = torch.tensor([0.0, 0.05, r * 0.999, r * 1.001, 1.0])
    w = blending_weights(d ** 2, sigma, eps)
    assert w[0] == pytest.approx(1 - eps)
    assert w[1] == pytest.approx(math.exp(-0.5) - eps, rel=1e-6)
    assert w[2] > 0 and w[3] == 0 and w[4] == 0


def test_candidate_pairs_match_brute_force():
    g = torch.Generator().manual_seed(1)
    centers = torch.rand(2, 10, 3, generator=g)
    pts = torch.rand(200, 3, generator=g)
    frame = torch.randint(2, (200,), generator=g)
    pi, ni = candidate_pairs(pts, frame, centers, 0.2)
    got = set(zip(pi.tolist(), ni.tolist()))
    d = (pts[:, None] - centers[frame]).norm(dim=-1)  # [P, N]
    want = set(zip(*[t.tolist() for t in (d < 0.2).nonzero(as_tuple=True)]))
    assert want <= got
    assert all(d[p, n] < 0.2 * 1.001 for p, n in got)


def test_ray_sphere_bounds():
    centers = torch.tensor([[[0.0, 0.0, 5.0], [0.0, 0.0, 7.0]]]).expand(3, 2, 3)
    o = torch.zeros(3, 3)
    d = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    near, far, hit = ray_sphere_bounds(o, d, centers, 0.5)
    assert hit.tolist() == [True, False, False]
    assert near[0] == pytest.approx(4.5) and far[0] == pytest.approx(7.5)
    assert near[1] == 0 and far[1] == 0


# ---- Eq. 5 / 7 and packing ---------------------------------------------------------------------------------------
def test_eq5_fusion_is_normalised_weighted_sum_sparse_equals_dense():
    feats = torch.tensor([[1.0, 0.0], [3.0, 2.0], [5.0, 5.0]])
    w = torch.tensor([0.5, 0.25, 0.2])
    point = torch.tensor([0, 0, 2])
    f, wsum = fuse_features(feats, w, point, 3)
    assert torch.allclose(f[0], (0.5 * feats[0] + 0.25 * feats[1]) / 0.75)
    assert torch.all(f[1] == 0) and wsum[1] == 0
    assert torch.allclose(f[2], feats[2])
    # dense layout [N=2, points=3, F]
    dense = torch.zeros(2, 3, 2)
    wd = torch.zeros(2, 3)
    dense[0, 0], dense[1, 0], dense[0, 2] = feats[0], feats[1], feats[2]
    wd[0, 0], wd[1, 0], wd[0, 2] = w[0], w[1], w[2]
    fd, wsd = fuse_features_dense(dense, wd)
    assert torch.allclose(fd, f) and torch.allclose(wsd, wsum)


def test_packing_roundtrip_and_widths():
    node = torch.tensor([2, 0, 2, 2, 1, 0])
    vals = torch.arange(6, dtype=torch.float32)[:, None] * torch.ones(1, 4)
    pk = Packing.build(node, 4)
    assert pk.counts.tolist() == [2, 1, 3, 0] and pk.width == 3
    packed = pk.pack(vals, 4)
    assert packed.shape == (4, 3, 4)
    assert packed[2, :, 0].tolist() == [0.0, 2.0, 3.0] and packed[3].abs().sum() == 0
    assert torch.equal(pk.unpack(packed), vals[pk.order])


def test_eq7_heads_ranges_and_view_dependence():
    torch.manual_seed(0)
    heads = RadianceHeads(feature_dim=8, width=16, pe_views=4)
    f = torch.randn(5, 8)
    v = torch.nn.functional.normalize(torch.randn(5, 3), dim=-1)
    sigma, rgb = heads.density(f), heads.color(f, v)
    assert sigma.shape == (5,) and bool((sigma >= 0).all())
    assert rgb.shape == (5, 3) and bool(((rgb > 0) & (rgb < 1)).all())
    assert not torch.allclose(heads.color(f, -v), rgb)  # G depends on v; H does not take v at all


# ---- positional encoding -----------------------------------------------------------------------------------------
def test_positional_encoding_shape_and_values():
    x = torch.tensor([[0.3, -1.0, 2.0]])
    for m in (6, 4, 12):
        assert positional_encoding(x, m).shape == (1, encoded_dim(3, m)) == (1, 3 * (1 + 2 * m))
    g = positional_encoding(x, 2)[0]
    assert torch.allclose(g[:3], x[0])  # gamma includes x itself
    assert torch.allclose(g[3:6], torch.sin(x[0])) and torch.allclose(g[6:9], torch.cos(x[0]))
    assert torch.allclose(g[9:12], torch.sin(2 * x[0])) and torch.allclose(g[12:15], torch.cos(2 * x[0]))
    t = torch.tensor([[0.5]])
    assert positional_encoding(t, 12).shape == (1, 25)


# ---- FPS ---------------------------------------------------------------------------------------------------------
def test_fps_deterministic_distinct_and_covering():
    tpl = sphere_template(600, radius=0.3)
    a = farthest_point_sampling(tpl.vertices, 32, seed=3)
    b = farthest_point_sampling(tpl.vertices, 32, seed=3)
    c = farthest_point_sampling(tpl.vertices, 32, seed=4)
    assert torch.equal(a, b) and not torch.equal(a, c)
    assert len(set(a.tolist())) == 32
    # coverage: every vertex is within the FPS covering radius; the radius is near the ideal for 32 points
    d = torch.cdist(tpl.vertices, tpl.vertices[a]).min(dim=1).values
    ideal = math.sqrt(4 * math.pi * 0.3 ** 2 / 32)  # spacing of 32 evenly spread points
    assert float(d.max()) < 1.0 * ideal
    # FPS beats random sampling's covering radius
    rnd = torch.randperm(600, generator=torch.Generator().manual_seed(0))[:32]
    assert float(d.max()) < float(torch.cdist(tpl.vertices, tpl.vertices[rnd]).min(dim=1).values.max())


# ---- batched MLP -------------------------------------------------------------------------------------------------
def test_batched_mlp_equals_per_node_loop():
    torch.manual_seed(0)
    mlp = BatchedMLP(5, [7, 16, 16, 4])
    x = torch.randn(5, 11, 7)
    bias = torch.randn(5, 11, 16)
    y = mlp(x, first_bias=bias)
    for i in range(5):
        h = x[i]
        for k, layer in enumerate(mlp.layers):
            h = h @ layer.weight[i] + layer.bias[i]
            if k == 0:
                h = h + bias[i]
            if k < 2:
                h = torch.relu(h)
        assert torch.allclose(y[i], h, atol=1e-5)
    with pytest.raises(AssertionError, match="expected"):
        BatchedLinear(5, 7, 3)(torch.randn(4, 2, 7))


# ---- Eq. 8 attention ---------------------------------------------------------------------------------------------
def test_pose_attention_map_properties():
    parents = (-1, 0, 1, 2, 0, 4)  # two chains from the root
    hops = kinematic_hop_distance(parents)
    assert hops[3, 5] == 5 and hops[2, 4] == 3 and torch.equal(hops, hops.T)
    W = pose_attention_map(parents, 1)
    assert torch.equal(W, W.T) and bool((W.diagonal() == 1).all())
    assert W[2].tolist() == [0, 1, 1, 1, 0, 0]
    assert torch.equal(pose_attention_map(parents, 0), torch.eye(6))
    assert bool((pose_attention_map(parents, 5) == 1).all())
    # a node skinned fully to joint 2 attends to joints 1, 2, 3 (hops=1); attention stays in [0, 1]
    omega = torch.zeros(2, 6)
    omega[0, 2] = 1.0
    omega[1, 2], omega[1, 5] = 0.5, 0.5
    att = node_pose_attention(omega, W)
    assert att[0].tolist() == [0, 1, 1, 1, 0, 0]
    assert bool((att <= 1).all() and (att >= 0).all()) and att[1, 4] == 0.5
    theta = torch.randn(3, 6, 3)
    cond = node_pose_condition(theta, att)  # Eq. 8
    assert cond.shape == (3, 2, 18)
    assert torch.allclose(cond[:, 0].reshape(3, 6, 3), att[0][None, :, None] * theta)


# ---- config ------------------------------------------------------------------------------------------------------
def test_config_defaults_presets_json_and_validation():
    c = ModelConfig()
    assert (c.num_nodes, c.sigma, c.eps, c.embed_dim, c.latent_dim, c.samples_per_ray) == (128, 0.05, 0.001, 32, 8, 64)
    assert (c.lambda_rec, c.lambda_trans, c.lambda_ebd, c.lambda_kl) == (1.0, 0.02, 0.1, 1e-5)
    assert (c.pe_coords, c.pe_views, c.pe_time) == (6, 4, 12)
    cpu = preset("cpu-mlp").model
    assert cpu.node_width < c.node_width and cpu.num_nodes == 128
    assert ModelConfig.from_json(cpu.to_json()) == cpu and cpu.field == "mlp"
    assert preset("cpu").model.field == "gaussians"
    # configs written before the grid field was removed (issue 28, schema_version 1) still read; a grid avatar is a
    # one-line error
    old = {**ModelConfig().to_json(), "schema_version": 1, "field": "mlp", "grid_levels": [8, 16, 32],
           "grid_channels": 4}
    old.pop("gaussians")
    assert ModelConfig.from_json(old) == ModelConfig()
    with pytest.raises(ValueError, match="field 'grid' .* was removed"):
        ModelConfig.from_json({**old, "field": "grid"})
    with pytest.raises(ValueError, match="unknown keys"):
        ModelConfig.from_json({**c.to_json(), "lamda_rec": 1.0})
    with pytest.raises(ValueError, match="latent"):
        ModelConfig(latent="vae")
    with pytest.raises(ValueError, match="eps"):
        ModelConfig(eps=1.5)


def test_reconstruction_loss_is_eq12_sum_at_the_reference_batch():
    from avatarctl.model.losses import reconstruction_loss

    g = torch.Generator().manual_seed(0)
    rgb, tgt = torch.rand(2048, 3, generator=g), torch.rand(2048, 3, generator=g)
    se = ((rgb - tgt) ** 2).sum()
    # Eq. 12 exactly at R = 2048; scaled by 2048 / R for other batch sizes (same per-ray weight)
    assert torch.allclose(reconstruction_loss(rgb, tgt, "sum", 2048), se)
    se512 = ((rgb[:512] - tgt[:512]) ** 2).sum()
    assert torch.allclose(reconstruction_loss(rgb[:512], tgt[:512], "sum", 2048), se512 * 4)
    assert torch.allclose(reconstruction_loss(rgb, tgt, "mean"), se / (2048 * 3))
    with pytest.raises(ValueError, match="reduction"):
        reconstruction_loss(rgb, tgt, "median")
    assert ModelConfig().rec_reduction == "sum"
    # a config saved before `rec_reduction` existed was trained with the mean, and reads back as such
    old = ModelConfig().to_json()
    del old["rec_reduction"]
    assert ModelConfig.from_json(old).rec_reduction == "mean"
    with pytest.raises(ValueError, match="rec_reduction"):
        ModelConfig(rec_reduction="max")


def test_the_gaussians_shading_is_an_option_and_old_configs_read_none():
    """`model.gaussians.shading`: "irradiance" by default, checked, kept through JSON; a Gaussian-field config saved
    before the option was trained unshaded and reads "none"."""
    cfg = ModelConfig(field="gaussians")
    assert cfg.gaussians.shading == "irradiance" and ModelConfig.from_json(cfg.to_json()) == cfg
    none = cfg.with_(gaussians={"shading": "none"})
    assert ModelConfig.from_json(none.to_json()).gaussians.shading == "none"
    old = cfg.to_json()
    del old["gaussians"]["shading"]
    assert ModelConfig.from_json(old).gaussians.shading == "none"
    with pytest.raises(ValueError, match="shading must be one of none, irradiance"):
        ModelConfig(field="gaussians", gaussians={"shading": "phong"})


def test_the_splats_low_pass_is_an_option_and_old_gaussian_configs_keep_3dgs_value():
    """`model.gaussians.low_pass` (px^2 added to each splat's 2D covariance): 0.1 by default, kept through JSON; a
    Gaussian-field config saved before the option was trained with 3DGS's 0.3 and reads back as such."""
    cfg = ModelConfig(field="gaussians")
    assert cfg.gaussians.low_pass == 0.1 and ModelConfig.from_json(cfg.to_json()) == cfg
    assert cfg.with_(gaussians={"per_node": 16}).gaussians.low_pass == 0.1  # a partial sub-config: the default
    old = cfg.to_json()
    del old["gaussians"]["low_pass"]
    assert ModelConfig.from_json(old).gaussians.low_pass == 0.3
    assert ModelConfig.from_json({**old, "field": "mlp"}).gaussians.low_pass == 0.1  # no splats to draw
    with pytest.raises(ValueError, match="low_pass must be >= 0"):
        ModelConfig(field="gaussians", gaussians={"low_pass": -0.1})
