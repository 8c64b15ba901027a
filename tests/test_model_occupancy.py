"""Empty-space skipping with per-node occupancy grids (model/occupancy.py): the selection rule, the EMA-max update,
and that the occupancy render equals the plain one when nothing is skipped."""

from __future__ import annotations

import torch

from fixtures.toy_model import conditioning, make, rays, small_cfg

from avatarctl.model.occupancy import UNSEEN, occupancy_estimate, select_samples, update_occupancy


def test_select_samples_threshold_and_unseen():
    density = torch.tensor([[0.0, 0.1, 5.0, 100.0, 100.0, 2.0]])
    unseen = torch.tensor([[True, False, False, False, False, False]])
    live = select_samples(density, unseen, threshold=0.5)
    assert live.tolist() == [[True, False, True, True, True, True]]


def test_estimate_takes_max_over_pairs_and_flags_unseen():
    occ = torch.tensor([UNSEEN, 0.2, 3.0, 0.0])
    cells = torch.tensor([0, 1, 2, 1, 3])
    point = torch.tensor([0, 0, 1, 1, 2])
    dens, unseen = occupancy_estimate(occ, cells, point, 4)
    assert torch.allclose(dens, torch.tensor([0.2, 3.0, 0.0, 0.0]))
    assert unseen.tolist() == [True, False, False, False]


def test_update_is_decayed_max_and_fills_unseen():
    occ = torch.tensor([UNSEEN, 10.0, 1.0, 7.0])
    update_occupancy(occ, torch.tensor([0, 1, 2, 2]), torch.tensor([0.3, 2.0, 0.5, 4.0]), decay=0.5)
    assert torch.allclose(occ, torch.tensor([0.3, 5.0, 4.0, 7.0]))  # cell 3 not observed: unchanged


def _pair(**kw):
    plain = make(small_cfg(**kw))
    occ = make(small_cfg(occupancy={"enabled": True}, **kw))
    occ.load_state_dict(plain.state_dict(), strict=False)  # same weights; the occupancy buffer stays unseen
    return plain.eval(), occ.eval()


def test_all_unseen_renders_exactly_like_the_plain_model():
    plain, occ = _pair()
    st = plain.node_state(conditioning(), "mean")
    with torch.no_grad():
        a, b = plain.render(rays(), st, torch.ones(3)), occ.render(rays(), st, torch.ones(3))
    assert torch.allclose(a.rgb, b.rgb, atol=1e-6) and torch.allclose(a.alpha, b.alpha, atol=1e-6)
    assert 0.9 * b.stats["samples"] < b.stats["live_samples"] <= b.stats["samples"]  # all but gap samples


def test_empty_grid_skips_every_sample_and_training_fills_cells():
    _, occ = _pair()
    st = occ.node_state(conditioning(), "mean")
    occ.occupancy.fill_(0.0)  # every cell seen empty
    with torch.no_grad():
        out = occ.render(rays(), st, torch.ones(3))
    assert out.stats["live_samples"] == 0 and float(out.alpha.max()) == 0.0
    occ.occupancy.fill_(UNSEEN)
    occ.train()
    st = occ.node_state(conditioning(), "posterior", generator=torch.Generator().manual_seed(0))
    out = occ.render(rays(), st, torch.ones(3), jitter=True, generator=torch.Generator().manual_seed(1))
    occ.losses(out, torch.zeros(len(rays()), 3), st).total.backward()
    seen = occ.occupancy >= 0
    assert 0 < int(seen.sum()) < seen.numel()  # the cells the samples visited now hold densities


def test_training_warm_up_evaluates_everything_then_skips_empty_cells():
    _, occ = _pair()
    occ.train()
    occ.occupancy.fill_(0.0)  # every cell seen empty
    st = occ.node_state(conditioning(), "mean")
    with torch.no_grad():
        warm = occ.render(rays(), st, torch.ones(3), generator=torch.Generator().manual_seed(0))
        occ.occupancy_updates.fill_(occ.cfg.occupancy.warmup)
        after = occ.render(rays(), st, torch.ones(3), generator=torch.Generator().manual_seed(0))
    assert warm.stats["live_samples"] == warm.stats["samples"]
    # past the warm-up only the exploration share of the samples is evaluated
    assert 0 < after.stats["live_samples"] < 3 * occ.cfg.occupancy.explore * after.stats["samples"]
