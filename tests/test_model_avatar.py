"""SlrfAvatar: sparse == dense (outputs and gradients), inference modes, ablation switches, state round-trip."""

from __future__ import annotations

import pytest
import torch

from fixtures.toy_model import conditioning, make, rays, small_cfg

from avatarctl.body.toy import sphere_template
from avatarctl.geometry.rays import RayBatch
from avatarctl.model import SlrfAvatar

# sparse and dense differ only by float reassociation (packed vs. dense bmm, index_add vs. sum)
ATOL_OUT = 1e-5
RTOL_GRAD, ATOL_GRAD = 1e-4, 1e-6


@pytest.mark.parametrize("variant,pack_block", [("slrf", 0), ("slrf", 16), ("slrf", 128), ("lbs_baseline", 128)])
def test_sparse_equals_dense_outputs_and_gradients(variant, pack_block):
    """pack_block 0 = the supplement's N x max S_i packing; 16 = several blocks per node; 128 = the default."""
    sparse = make(small_cfg(variant=variant, sparse=True, pack_block=pack_block))
    dense = make(small_cfg(variant=variant, sparse=False))
    dense.load_state_dict(sparse.state_dict())
    rb, cond, bg = rays(), conditioning(), torch.tensor([1.0, 1.0, 1.0])
    target = torch.rand(len(rb), 3, generator=torch.Generator().manual_seed(1))
    outs = {}
    for name, m in (("sparse", sparse), ("dense", dense)):
        st = m.node_state(cond, "posterior", generator=torch.Generator().manual_seed(7))
        out = m.render(rb, st, bg)
        m.losses(out, target, st).total.backward()
        outs[name] = out
    s, d = outs["sparse"], outs["dense"]
    if variant == "slrf" and pack_block:
        assert s.stats["packed_slots"] < s.stats["pairs"] + pack_block * 24  # < one padded block per node
    assert 0 < s.stats["pairs"] < d.stats["pairs"]  # the sparse path evaluates fewer node-sample pairs
    assert s.stats["hit_rays"] > 50 and float(s.alpha.detach().max()) > 0
    for k in ("rgb", "alpha", "depth"):
        assert torch.allclose(getattr(s, k), getattr(d, k), atol=ATOL_OUT), k
    dp = dict(dense.named_parameters())
    n_checked = 0
    for name, p in sparse.named_parameters():
        assert p.grad is not None, name
        assert torch.allclose(p.grad, dp[name].grad, rtol=RTOL_GRAD, atol=ATOL_GRAD), name
        n_checked += int(p.grad.abs().sum() > 0)
    assert n_checked >= 4


def test_missed_rays_return_background_and_chunking_is_exact():
    m = make(small_cfg())
    st = m.node_state(conditioning(), "mean")
    rb = rays(40)
    away = RayBatch(torch.tensor([[0.0, -2.0, 0.0]]).expand(3, 3).contiguous(),
                    torch.tensor([[0.0, -1.0, 0.0]]).expand(3, 3).contiguous(), torch.zeros(3, dtype=torch.long))
    both = RayBatch.cat([rb, away])
    bg = torch.tensor([0.2, 0.4, 0.6])
    with torch.no_grad():
        full = m.render(both, st, bg)
        chunked = m.render(both, st, bg, chunk=7)
    assert torch.all(full.alpha[-3:] == 0) and torch.allclose(full.rgb[-3:], bg.expand(3, 3))
    assert torch.allclose(full.rgb, chunked.rgb, atol=1e-6) and torch.allclose(full.alpha, chunked.alpha, atol=1e-6)
    assert chunked.stats["hit_rays"] == full.stats["hit_rays"]


def test_zero_density_without_nodes_in_range():
    m = make(small_cfg())
    st = m.node_state(conditioning(), "mean")
    far_pts = torch.stack([torch.tensor([3.0, 0.0, 0.0]), st.centers[0, 0] + 0.01])  # far away / near node 0
    # (the sphere's centre is 0.3 m from every node, beyond the 0.186 m support: also empty)
    far_pts = torch.cat([far_pts, torch.zeros(1, 3)])
    with torch.no_grad():
        _, sigma, _ = m.query(far_pts, torch.tensor([[0.0, 1.0, 0.0]]).expand(3, 3), torch.zeros(3, dtype=torch.long),
                              st)
    assert sigma[0] == 0 and sigma[1] > 0 and sigma[2] == 0


def test_inference_modes():
    m = make(small_cfg())
    c1 = conditioning(times=(0.0, 0.5))
    c2 = conditioning(times=(0.9, 0.1))
    with torch.no_grad():
        # zero mode ignores time (encoder skipped)
        z1, z2 = m.node_state(c1, "zero"), m.node_state(c2, "zero")
        assert torch.equal(z1.delta_n, z2.delta_n) and torch.equal(z1.embed, z2.embed) and z1.mu is None
        # mean mode: deterministic, depends on time
        a, b = m.node_state(c1, "mean"), m.node_state(c1, "mean")
        assert torch.equal(a.embed, b.embed) and a.mu is not None
        assert not torch.allclose(a.embed, m.node_state(c2, "mean").embed)
        # sample mode: seeded by the generator
        s1 = m.node_state(c1, "sample", torch.Generator().manual_seed(3))
        s2 = m.node_state(c1, "sample", torch.Generator().manual_seed(3))
        s3 = m.node_state(c1, "sample", torch.Generator().manual_seed(4))
        assert torch.equal(s1.embed, s2.embed) and not torch.equal(s1.embed, s3.embed)
        # posterior: reparameterised sample around mu
        p = m.node_state(c1, "posterior", torch.Generator().manual_seed(3))
        assert torch.allclose(p.mu, a.mu) and not torch.equal(p.embed, a.embed)
    with pytest.raises(ValueError, match="mode"):
        m.node_state(c1, "train")


def test_posterior_is_differentiable_and_losses_have_all_terms():
    m = make(small_cfg())
    st = m.node_state(conditioning(), "posterior", torch.Generator().manual_seed(0))
    out = m.render(rays(48), st, torch.ones(3), jitter=True, generator=torch.Generator().manual_seed(0))
    L = m.losses(out, torch.zeros(48, 3), st)
    f = L.as_floats()
    assert set(f) == {"total", "rec", "trans", "ebd", "kl", "mse"} and all(v > 0 for v in f.values())
    c = m.cfg
    # Eq. 12 as written: sum over rays and channels, at the reference batch of 2048 rays (here 48 rays)
    assert f["rec"] == pytest.approx(f["mse"] * 3 * 48 * (c.rec_reference_rays / 48), rel=1e-5)
    assert f["total"] == pytest.approx(c.lambda_rec * f["rec"] + c.lambda_trans * f["trans"] +
                                       c.lambda_ebd * f["ebd"] + c.lambda_kl * f["kl"], rel=1e-5)
    L.total.backward()
    assert m.latent.encoder.layers[0].weight.grad.abs().sum() > 0  # KL + reparameterisation reach the encoder


def test_ablation_switches():
    cond = conditioning()
    no_dn = make(small_cfg(use_delta_n=False)).node_state(cond, "mean")
    assert torch.all(no_dn.delta_n == 0) and no_dn.embed.abs().sum() > 0
    no_e = make(small_cfg(use_embedding=False)).node_state(cond, "mean")
    assert torch.all(no_e.embed == 0) and no_e.delta_n.abs().sum() > 0
    det = make(small_cfg(latent="deterministic"))
    assert det.latent.encoder is None
    d1, d2 = det.node_state(cond, "posterior"), det.node_state(conditioning(times=(0.7, 0.2)), "mean")
    assert d1.mu is None and torch.equal(d1.embed, d2.embed)  # pose regression: no time, no latent
    assert det.losses(det.render(rays(16), d1, torch.ones(3)), torch.zeros(16, 3), d1).kl == 0
    pf = make(small_cfg(latent="per_frame"), num_frames=3)
    a = pf.node_state(conditioning(ids=(0, 1)), "mean")
    b = pf.node_state(conditioning(ids=(2, 1)), "mean")  # same time/pose, a different frame code
    assert not torch.allclose(a.embed[0], b.embed[0]) and torch.allclose(a.embed[1], b.embed[1])
    with pytest.raises(ValueError, match="per_frame"):
        pf.node_state(conditioning(ids=(-1, 1)), "mean")
    assert pf.node_state(conditioning(ids=(-1, -1)), "zero").mu is None  # novel poses need no code
    base = make(small_cfg(variant="lbs_baseline"))
    bs = base.node_state(cond, "mean")
    assert torch.all(bs.delta_n == 0) and torch.all(bs.embed == 0) and not hasattr(base, "fields")
    assert torch.equal(bs.centers, no_dn.centers)  # same nodes, Eq. 2 positions
    # the baseline's field is pose-only: time does not change the rendering
    with torch.no_grad():
        r1 = base.render(rays(32), base.node_state(conditioning(times=(0.0, 0.5)), "mean"), torch.ones(3))
        r2 = base.render(rays(32), base.node_state(conditioning(times=(0.9, 0.1)), "mean"), torch.ones(3))
    assert torch.equal(r1.rgb, r2.rgb)


def test_nodes_are_buffers_and_state_dict_round_trips():
    m = make(small_cfg())
    names = dict(m.named_buffers())
    assert names["node_rest"].shape == (24, 3) and names["node_skin_weights"].shape == (24, 2)
    assert torch.allclose(names["node_skin_weights"].sum(-1), torch.ones(24))
    # nodes lie on the template surface (they are template vertices)
    tpl = sphere_template(300)
    assert torch.allclose(names["node_rest"], tpl.vertices[names["node_vertex_index"]])
    m2 = SlrfAvatar(small_cfg(), tpl, num_frames=4, seed=5)
    m2.load_state_dict(m.state_dict())
    rb, cond = rays(32), conditioning()
    with torch.no_grad():
        a = m.render(rb, m.node_state(cond, "mean"), torch.ones(3))
        b = m2.render(rb, m2.node_state(cond, "mean"), torch.ones(3))
    assert torch.equal(a.rgb, b.rgb)


def test_node_transforms_follow_the_pose():
    m = make(small_cfg(use_delta_n=False))
    st = m.node_state(conditioning(bends=(0.0, 1.0)), "zero")
    upper = m.node_skin_weights[:, 1] > 0.99
    lower = m.node_skin_weights[:, 0] > 0.99
    assert upper.any() and lower.any()
    # bending joint 1 moves the upper nodes, not the lower ones (Eq. 1-2)
    moved = (st.centers[1] - st.centers[0]).norm(dim=-1)
    assert float(moved[upper].min()) > 0.05 and float(moved[lower].max()) < 0.01


def test_knock_out_zeroes_the_chosen_node_variables_only():
    import torch

    m = make(small_cfg(occupancy={"enabled": False})).eval()
    with torch.no_grad():
        for p in m.parameters():  # a model whose decoder outputs are far from zero
            p.add_(0.05 * torch.randn_like(p))
        st = m.node_state(conditioning(), mode="mean")
        assert st.delta_n.abs().max() > 0 and st.embed.abs().max() > 0
        same = m.knock_out(st)
        assert torch.equal(same.centers, st.centers) and torch.equal(same.embed, st.embed)
        no_dn = m.knock_out(st, delta_n=True)
        assert torch.equal(no_dn.embed, st.embed) and no_dn.delta_n.abs().max() == 0
        skinned = m.knock_out(st, delta_n=True, embedding=True)
        assert skinned.embed.abs().max() == 0 and torch.equal(skinned.centers, no_dn.centers)
        # the same weights trained without Delta n / e (the ablation's forward pass) give the same nodes
        abl = make(small_cfg(occupancy={"enabled": False}, use_delta_n=False, use_embedding=False)).eval()
        abl.load_state_dict(m.state_dict())
        ref = abl.node_state(conditioning(), mode="mean")
        assert torch.allclose(skinned.centers, ref.centers) and torch.equal(skinned.embed, ref.embed)
        assert (st.centers - skinned.centers).norm(dim=-1).max() > 1e-4
        bg = torch.zeros(3)
        r = rays()
        assert not torch.allclose(m.render(r, st, bg).rgb, m.render(r, skinned, bg).rgb)


def test_novel_pose_latent_zero_or_the_mean_of_the_training_posterior_means():
    """model.novel_latent (issue 18): "zero" is the paper's z = 0 at novel poses; "train_mean" uses the mean over the
    training frames of mu_i, per node, set from the weights of the moment (the fit does it before each checkpoint)."""
    from avatarctl.model.deformer import node_pose_condition
    from avatarctl.stages.common import latent_for

    train = conditioning(bends=(0.0, 0.6, 0.3), times=(0.0, 1 / 3, 2 / 3), ids=(0, 1, 2))
    novel = conditioning(bends=(0.9, 0.1), times=(0.0, 0.0), ids=(-1, -1))
    paper = make(small_cfg(novel_latent="zero"))
    assert not hasattr(paper.latent, "latent_mean")
    paper.set_latent_mean(train)  # a no-op
    assert torch.equal(paper.node_state(novel, "novel").delta_n, paper.node_state(novel, "zero").delta_n)

    m = make(small_cfg(novel_latent="train_mean"))
    assert torch.all(m.latent.latent_mean == 0)  # before it is set: z = 0 as in the paper
    assert torch.equal(m.node_state(novel, "novel").embed, m.node_state(novel, "zero").embed)
    m.set_latent_mean(train)
    mu = m.node_state(train, "mean").mu  # [3, N, Z]
    assert torch.allclose(m.latent.latent_mean, mu.mean(0), atol=1e-6) and m.latent.latent_mean.abs().sum() > 0
    got = m.node_state(novel, "novel")
    theta = node_pose_condition(novel.pose_features, m.pose_attention).transpose(0, 1)  # [N, 2, 3J]
    z = m.latent.latent_mean[:, None].expand(-1, 2, -1)
    want = m.latent.decoder(torch.cat([z, theta], -1)).transpose(0, 1)  # Eq. 10 at z = mean mu
    assert torch.allclose(got.delta_n, want[..., :3], atol=1e-6) and torch.allclose(got.embed, want[..., 3:], atol=1e-6)
    assert not torch.allclose(got.delta_n, m.node_state(novel, "zero").delta_n)
    # saved with the weights; a checkpoint from before the option loads with z = 0
    again = make(small_cfg(novel_latent="train_mean"))
    again.load_state_dict(m.state_dict())
    assert torch.equal(again.latent.latent_mean, m.latent.latent_mean)
    old = {k: v for k, v in m.state_dict().items() if not k.endswith("latent_mean")}
    again.load_state_dict(old)
    assert torch.all(again.latent.latent_mean == 0)
    assert latent_for("auto", False) == "novel" and latent_for("auto", True) == "mean"
    with pytest.raises(ValueError, match="novel_latent"):
        small_cfg(novel_latent="mean")


def test_checkpoints_of_the_removed_coarse_to_fine_encoding_load_when_fully_open():
    """The coarse-to-fine gamma(p) (`pe_anneal_steps`) was removed in issue 30; its level buffer, in checkpoints
    written before, is dropped when fully open (the plain encoding), an error otherwise."""
    m = make(small_cfg())
    state = m.state_dict()
    assert not any(k.endswith("pe_level") for k in state)
    again = make(small_cfg())
    again.load_state_dict({**state, "fields.pe_level": torch.tensor(float(m.cfg.pe_coords))})
    assert all(torch.equal(a, b) for a, b in zip(again.state_dict().values(), state.values()))
    with pytest.raises(ValueError, match="not fully open"):
        again.load_state_dict({**state, "fields.pe_level": torch.tensor(2.0)})
