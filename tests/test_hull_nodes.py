"""Hull nodes (fit/hull_nodes.py, `model.hull`): carving, the persistence filter, placement, the model."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from avatarctl.fit.hull_nodes import (HullSurvey, auto_hull_nodes, mesh_volume, off_body_canonical, persistent_cells,
                                     worn_cells)
from avatarctl.geometry.cameras import Camera, look_at
from avatarctl.geometry.hull import carve
from avatarctl.model import ModelConfig
from avatarctl.model.config import HullConfig


def _ring_cameras(n: int = 6, size: int = 96) -> list[Camera]:
    cams = []
    for i in range(n):
        a = 2 * np.pi * i / n
        R, T = look_at(np.array([3 * np.cos(a), 3 * np.sin(a), 0.4]), np.zeros(3))
        K = np.array([[120.0, 0, size / 2], [0, 120.0, size / 2], [0, 0, 1]])
        cams.append(Camera(f"c{i}", K, R, T, size, size))
    return cams


def _sphere_mask(cam: Camera, centre: np.ndarray, radius: float) -> np.ndarray:
    """Silhouette of a sphere: pixels whose ray passes within `radius` of `centre`."""
    v, u = np.mgrid[0:cam.height, 0:cam.width]
    xy = (np.stack([u, v], -1) - cam.K[:2, 2]) / np.diag(cam.K)[:2]
    d = np.concatenate([xy, np.ones(xy.shape[:-1] + (1,))], -1) @ cam.R  # world ray directions
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    o = cam.center
    oc = centre - o
    t = d @ oc
    return np.linalg.norm(o + t[..., None] * d - centre, axis=-1) <= radius


def test_carving_recovers_a_sphere():
    cams = _ring_cameras()
    centre, r = np.array([0.1, -0.05, 0.0]), 0.3
    pts = carve(cams, [_sphere_mask(c, centre, r) for c in cams], centre - 0.6, centre + 0.6, 0.04)
    d = np.linalg.norm(pts - centre, axis=-1)
    assert len(pts) > 100
    assert d.max() < r + 0.12  # a 6-view hull is a little larger than the sphere, never much
    assert len(pts) * 0.04 ** 3 == pytest.approx(4 / 3 * np.pi * r ** 3, rel=0.5)
    inner = np.linalg.norm(np.stack(np.meshgrid(*[np.arange(-0.58, 0.6, 0.04)] * 3, indexing="ij"), -1), axis=-1)
    assert len(pts) >= (inner < r - 0.05).sum()  # everything well inside is kept


def test_carving_keeps_only_what_the_body_does_not_explain():
    """Tight clothing: the masks are the body's silhouettes, so every hull voxel (phantoms included) projects onto
    the body in every view and none is kept. A second solid the body does not explain (a garment) keeps its own
    voxels, not the body's."""
    cams = _ring_cameras()
    body, garment, r = np.array([0.0, 0.0, 0.0]), np.array([0.0, 0.0, 0.8]), 0.25
    body_sil = [_sphere_mask(c, body, r) for c in cams]
    lo, hi = np.array([-0.6, -0.6, -0.6]), np.array([0.6, 0.6, 1.4])
    assert len(carve(cams, body_sil, lo, hi, 0.04)) > 100
    assert len(carve(cams, body_sil, lo, hi, 0.04, explained=body_sil)) == 0
    masks = [b | _sphere_mask(c, garment, r) for b, c in zip(body_sil, cams)]
    full = carve(cams, masks, lo, hi, 0.04)
    kept = carve(cams, masks, lo, hi, 0.04, explained=body_sil)
    near_garment = lambda p: np.linalg.norm(p - garment, axis=-1) < r  # noqa: E731
    assert near_garment(kept).sum() == near_garment(full).sum() > 50  # the garment's inside: all kept
    assert (np.linalg.norm(kept - body, axis=-1) < r - 0.05).sum() == 0  # the body's inside: none


def test_mesh_volume_of_a_sphere():
    from avatarctl.body.toy import sphere_template

    tpl = sphere_template(2000, radius=0.3)
    assert mesh_volume(tpl.vertices, tpl.faces) == pytest.approx(4 / 3 * np.pi * 0.3 ** 3, rel=0.02)


@pytest.mark.parametrize("cells, k", [(0, 0), (7, 0), (8, 32), (500, 32)])
def test_auto_rule_says_yes_from_a_tenth_of_the_body_volume(cells, k):
    """`hull_nodes = "auto"`: 32 of 128 nodes once the persistent off-body cells hold >= 10 % of the body volume
    (here 8 cells of 5 cm = 1 litre of a 10-litre body), else none."""
    survey = HullSurvey(cells=np.zeros((cells, 3)), cell=0.05, frames=6, body_volume=0.01)
    assert auto_hull_nodes(survey, ModelConfig(hull=HullConfig(nodes="auto")).hull_auto_nodes, min_volume=0.1) == k
    assert ("8 persistent off-body cells" in survey.describe()) == (cells == 8)


def test_persistence_drops_what_one_frame_shows():
    rng = np.random.default_rng(0)
    garment = [np.array([0.3, 0.0, -0.4]) + 0.01 * rng.standard_normal((50, 3)) for _ in range(6)]
    garment[2] = np.concatenate([garment[2], np.array([[2.0, 2.0, 2.0]])])  # a phantom in one frame
    kept = persistent_cells(garment, cell=0.05, min_frames=2)
    assert len(kept) >= 1 and np.abs(kept - [0.3, 0.0, -0.4]).max() < 0.06
    assert not (np.linalg.norm(kept - 2.0, axis=-1) < 0.1).any()
    assert persistent_cells([], 0.05, 2).shape == (0, 3)


def test_only_cells_connected_to_the_body_are_worn():
    """A skirt's shell of cells reaching out from the legs is kept whole, its far hem included; a floor patch as
    large, 40 cm from the body, is dropped, and so is a lone cell just beyond reach."""
    body = np.stack(np.meshgrid(np.linspace(-0.1, 0.1, 5), np.linspace(-0.1, 0.1, 5), np.linspace(-0.8, 0.6, 30)),
                    -1).reshape(-1, 3)  # a column of vertices
    a, t = np.meshgrid(np.linspace(0, 2 * np.pi, 120, endpoint=False), np.linspace(0, 1, 40))
    r, z = 0.15 + 0.3 * t, -0.1 - 0.4 * t  # a cone from the hips out to a hem 0.35 m from the column
    skirt = np.stack([r * np.cos(a), r * np.sin(a), z], -1).reshape(-1, 3)
    skirt = np.unique(np.floor(skirt / 0.05), axis=0) * 0.05 + 0.025  # one point per 5 cm cell
    floor = np.stack(np.meshgrid(np.arange(12), np.arange(12)), -1).reshape(-1, 2) * 0.05 + [0.6, 0.0]
    floor = np.concatenate([floor, np.full((len(floor), 1), -1.0)], 1) + 0.025
    lone = np.array([[0.0, 0.26, 0.3]])  # 0.16 m from the column
    kept, dropped = worn_cells(np.concatenate([skirt, floor, lone]), 0.05, body, reach=0.14)
    assert len(kept) == len(skirt) and dropped == len(floor) + 1
    assert np.allclose(np.sort(kept, axis=0), np.sort(skirt, axis=0))
    assert worn_cells(np.zeros((0, 3)), 0.05, body, 0.14)[0].shape == (0, 3)
    survey = HullSurvey(cells=kept, cell=0.05, frames=6, body_volume=0.06, apart=dropped)
    assert f"{dropped} more apart from the body, dropped" in survey.describe()


@pytest.mark.parametrize("frames, need", [(1, 1), (2, 2), (10, 2), (24, 4), (80, 12)])
def test_persistence_needs_15_percent_of_the_frames_and_two_unless_there_is_one(frames, need):
    from avatarctl.fit.hull_nodes import persistence_threshold

    assert persistence_threshold(frames, 0.15) == need


def test_farthest_point_sampling_starts_where_the_existing_nodes_are_not():
    from avatarctl.model.deformer import farthest_point_sampling

    existing = torch.zeros(1, 3)
    pts = torch.tensor([[0.1, 0, 0], [1.0, 0, 0], [0.9, 0, 0], [0, 0.5, 0]])
    idx = farthest_point_sampling(pts, 2, existing=existing)
    assert idx.tolist() == [1, 3]
    with pytest.raises(ValueError, match=r"need 0 < n <= 4 points"):
        farthest_point_sampling(pts, 5, existing=existing)


def test_off_body_points_go_back_through_their_vertex_transform():
    V = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    T = torch.eye(4, dtype=torch.float64).repeat(2, 1, 1)
    T[:, :3, 3] = torch.tensor([0.5, 0.0, 0.0])  # the posed body is the canonical one shifted by +0.5 in x
    posed = V + torch.tensor([0.5, 0.0, 0.0], dtype=torch.float64)
    pts = np.array([[0.5, 0.0, 0.05], [1.2, 0.0, 1.0]])  # on the body / 0.7 m off it
    out = off_body_canonical(pts, posed, T, posed.numpy(), min_dist=0.3)
    assert out.shape == (1, 3) and np.allclose(out[0], [0.7, 0.0, 1.0])


def test_model_takes_hull_nodes_and_a_checkpoint_restores_them():
    from fixtures.toy_model import small_cfg

    from avatarctl.body.toy import sphere_template
    from avatarctl.model import SlrfAvatar

    cfg = small_cfg(hull={"nodes": 4})
    tpl = sphere_template(300)
    rest = torch.tensor([[0.6, 0.0, 0.0], [-0.6, 0.0, 0.0], [0.0, 0.6, 0.0], [0.0, -0.6, 0.0]])
    model = SlrfAvatar(cfg, tpl, num_frames=2, seed=0, hull_nodes=(rest, torch.tensor([0, 1, 2, 3])))
    assert model.node_rest.shape == (24, 3) and torch.equal(model.node_rest[-4:], rest)
    assert torch.equal(model.node_skin_weights[-1], tpl.skin_weights[3].float())
    loaded = SlrfAvatar(cfg, tpl, num_frames=2, seed=0)  # placeholders, as a checkpoint load builds it
    assert not torch.equal(loaded.node_rest[-4:], rest)
    loaded.load_state_dict(model.state_dict())
    assert torch.equal(loaded.node_rest, model.node_rest)
    with pytest.raises(ValueError, match="hull_nodes must be"):
        SlrfAvatar(cfg, tpl, num_frames=2, seed=0, hull_nodes=(rest[:3], torch.tensor([0, 1, 2])))


def test_config_checks_hull_nodes():
    with pytest.raises(ValueError, match="hull.nodes"):
        ModelConfig(num_nodes=16, hull=HullConfig(nodes=16))
    with pytest.raises(ValueError, match="slrf variant"):
        ModelConfig(hull=HullConfig(nodes=8), variant="lbs_baseline")


def test_config_takes_auto_and_says_how_to_fix_a_typo():
    from avatarctl.errors import InputError
    from avatarctl.fit.config import resolve_fit_config

    from avatarctl.fit.config import preset

    auto = HullConfig(nodes="auto")
    assert ModelConfig(hull=auto).hull.nodes == "auto"
    assert ModelConfig(hull=auto, variant="lbs_baseline").hull.nodes == "auto"  # no nodes: nothing to decide
    assert ModelConfig.from_json(ModelConfig(hull=auto).to_json()).hull == auto
    with pytest.raises(ValueError, match=r"nodes must be an int >= 0 or 'auto'"):
        HullConfig(nodes="aut")
    with pytest.raises(ValueError, match="auto_fraction"):
        HullConfig(auto_fraction=1.0)
    assert ModelConfig(num_nodes=12, hull=auto).hull_auto_nodes == 3
    with pytest.raises(ValueError, match="would place 1 of num_nodes=1 nodes off the body"):
        ModelConfig(num_nodes=1, hull=auto)
    assert preset("paper").model.hull.nodes == 0  # the paper's placement (Sec. 3.1)
    assert preset("cpu").model.hull.nodes == "auto"
    for key in ("model.hull.nodes", "model.hull_nodes"):  # the flat key of older configs names the same field
        for text, value in (("auto", "auto"), ("AUTO", "auto"), ("32", 32), ("0", 0)):
            assert resolve_fit_config("cpu", overrides=[f"{key}={text}"]).model.hull.nodes == value
    cfg = resolve_fit_config("cpu", overrides=["model.hull.nodes=auto"])
    assert resolve_fit_config("cpu", overrides=["model.hull.nodes=auto", "model.hull.nodes=8"]).model.hull.nodes == 8
    assert cfg.model.hull.nodes == "auto"
    with pytest.raises(InputError, match="as int or auto"):
        resolve_fit_config("cpu", overrides=["model.hull.nodes=many"])


@pytest.mark.parametrize("skirt, setting, note", [
    (0.5, "4", "-> 4 of 32 nodes placed off the body"),
    (0.0, "4", "-> 0 of 32 nodes placed off the body, 4 more on the surface"),
    (0.5, "auto", "(hull_nodes=auto) -> 8 of 32 nodes placed off the body"),
    (0.0, "auto", "-> none (hull_nodes=auto: all 32 nodes on the surface)"),
])
def test_fit_places_hull_nodes_where_the_capture_shows_a_skirt(tmp_path, skirt, setting, note):
    """The loop surveys the masks, decides ("auto": 8 = 32 / 4 nodes with the skirt, none without) and logs the
    figure it decided on; the checkpoint brings the node positions back. Without the skirt the toy capture's masks
    are its body's silhouettes: nothing is off the body, an explicit K falls back to the surface."""
    import json

    from fixtures.toy_capture import make_toy_capture

    from avatarctl.fit.checkpoint import load_avatar
    from avatarctl.project import Project
    from avatarctl.stages import fit, ingest
    from avatarctl.stages.fit import FitRequest
    from avatarctl.stages.ingest import IngestConfig

    cap, proj = make_toy_capture(tmp_path / "cap", skirt=skirt), tmp_path / "proj"
    ingest.run(proj, IngestConfig(capture=cap, project=proj, contact_sheet=False))
    result = fit.run(proj, FitRequest(preset="micro", iters=2, device="cpu", overrides=(
        f"model.hull.nodes={setting}", "val_every=0")), handle_sigint=False)
    notes = [json.loads(line).get("note", "") for line in (proj / "fit" / "log.jsonl").read_text().splitlines()]
    logged = next(n for n in notes if n.startswith("hull: "))
    assert logged.endswith(note), logged
    assert result.hull_nodes == logged
    record = Project.open(proj).last("fit")
    assert record is not None and record.summary["hull_nodes"] == logged
    av = load_avatar(Project.open(proj), device="cpu")
    ckpt = torch.load(proj / "fit" / "checkpoints" / "latest.pt", map_location="cpu", weights_only=False)
    assert torch.equal(av.model.node_rest, ckpt["model"]["node_rest"])
    assert av.model.node_rest.shape[0] == av.model.cfg.num_nodes
    if skirt:  # the off-body nodes: beyond the 0.3 m sphere, at the skirt's height (z -0.25 to -0.05 m; two
        # opposite training views do not carve the skirt's depth, so some sit beyond its 0.5 m radius)
        k = int(note.split("-> ")[1].split(" of")[0])
        r = torch.linalg.norm(av.model.node_rest[-k:, :2], dim=-1)
        z = av.model.node_rest[-k:, 2]
        assert (r > 0.35).all() and (z > -0.35).all() and (z < 0.05).all(), (r, z)
    else:
        from avatarctl.model.deformer import farthest_point_sampling  # the paper's placement, bit for bit

        idx = farthest_point_sampling(av.template.vertices, 32, av.fit_config.seed)
        if setting == "auto":
            assert torch.equal(av.model.node_rest, av.template.vertices.float()[idx])


def test_resuming_an_auto_fit_keeps_its_nodes(tmp_path):
    """A resumed `hull_nodes=auto` fit does not survey again: the checkpoint's node positions come back as they
    were and the run continues from them."""
    from fixtures.toy_capture import make_toy_capture

    from avatarctl.stages import fit, ingest
    from avatarctl.stages.fit import FitRequest
    from avatarctl.stages.ingest import IngestConfig

    cap, proj = make_toy_capture(tmp_path / "cap", skirt=0.5), tmp_path / "proj"
    ingest.run(proj, IngestConfig(capture=cap, project=proj, contact_sheet=False))
    first = fit.run(proj, FitRequest(preset="micro", iters=2, device="cpu", overrides=(
        "model.hull.nodes=auto", "val_every=0")), handle_sigint=False)
    rest = torch.load(first.checkpoint, map_location="cpu", weights_only=True)["model"]["node_rest"]
    again = fit.run(proj, FitRequest(iters=3, device="cpu", resume=True), handle_sigint=False)
    assert again.step == 3 and again.hull_nodes is None  # nothing placed this run
    assert first.hull_nodes is not None and "-> 8 of 32 nodes placed off the body" in first.hull_nodes
    assert torch.equal(torch.load(again.checkpoint, map_location="cpu", weights_only=True)["model"]["node_rest"], rest)


def test_a_tracked_garment_gets_many_small_patches_with_the_same_gaussians():
    """`hull.tracked_nodes` (the cpu preset: 256): `for_tracked_garment` gives N = 256 nodes, half off the body, and
    scales the Gaussians per node to keep their total; 0 (or N already) leaves the model as it is."""
    from avatarctl.fit.config import preset, resolve_fit_config

    cpu = preset("cpu").model
    assert cpu.hull.tracked_nodes == 256 and preset("cpu-mlp").model.hull.tracked_nodes == 0
    g = cpu.for_tracked_garment()
    assert (g.num_nodes, g.hull.auto_fraction, g.hull_auto_nodes) == (256, 0.5, 128)
    assert g.num_nodes * g.gaussians.per_node == cpu.num_nodes * cpu.gaussians.per_node == 24_576
    assert (g.hull.nodes, g.field, g.cvae_width) == (cpu.hull.nodes, cpu.field, cpu.cvae_width)  # nothing else
    assert g.for_tracked_garment() is g  # N is already 256: a saved config decided once stays as it is
    off = resolve_fit_config("cpu", overrides=["model.hull.tracked_nodes=0"]).model
    assert off.hull.tracked_nodes == 0 and off.for_tracked_garment() is off
    with pytest.raises(ValueError, match="tracked_nodes must be an int >= 0"):
        HullConfig(tracked_nodes=-1)


def test_a_fresh_fit_decides_its_model_from_the_hull_survey(monkeypatch):
    """`fit.loop._decide_hull`: the model of `for_tracked_garment` (its hull nodes placed again for it) only where the
    fit will track a garment from enough views: hull nodes found, `track` on, four training views or more, one
    process."""
    from dataclasses import replace
    from types import SimpleNamespace

    from avatarctl.fit import loop
    from avatarctl.fit.config import resolve_fit_config

    found: list = []

    def survey(model_cfg, seed, capture, body, template, frames, views):
        found.append(model_cfg)
        return (SimpleNamespace() if garment else None), f"hull: {model_cfg.num_nodes} nodes"

    monkeypatch.setattr(loop, "_place_hull_nodes", survey)
    assert loop.TRACKED_NODES_MIN_VIEWS == 4
    four = SimpleNamespace(split=SimpleNamespace(train_views=("cam00", "cam01", "cam02", "cam03")))
    three = SimpleNamespace(split=SimpleNamespace(train_views=("cam00", "cam01", "cam02")))  # too few: 128 nodes
    cpu = resolve_fit_config("cpu")
    garment = True
    cfg, hull, note = loop._decide_hull(cpu, four, None, None, [0, 1], 1)
    assert hull is not None and cfg.model == cpu.model.for_tracked_garment() and cfg.model.num_nodes == 256
    assert cfg.model.track_refine.enabled is True  # "auto" decided on with the garment's model
    assert [m.num_nodes for m in found] == [128, 256]  # surveyed with the preset's model, placed with the garment's
    assert note == "hull: 256 nodes (garment tracking: 96 Gaussians per node)"
    for case, capture, ranks in (("track off", four, 1), ("three views", three, 1), ("two ranks", four, 2),
                                 ("tracked_nodes 0", four, 1)):
        found.clear()
        base = replace(cpu, track=False) if case == "track off" else \
            resolve_fit_config("cpu", overrides=["model.hull.tracked_nodes=0"]) if case == "tracked_nodes 0" else cpu
        cfg, hull, note = loop._decide_hull(base, capture, None, None, [0, 1], ranks)
        assert cfg.model == base.model.with_(track_refine={"enabled": False}), case  # "auto" decided off
        assert cfg == replace(base, model=cfg.model) and len(found) == 1 and note == "hull: 128 nodes", case
    garment = False  # no loose garment: the preset's model, hull nodes none
    found.clear()
    cfg, hull, _ = loop._decide_hull(cpu, four, None, None, [0, 1], 1)
    assert cfg.model == cpu.model.with_(track_refine={"enabled": False}) and hull is None and len(found) == 1
    paper = resolve_fit_config("paper")  # hull nodes off: no survey at all
    assert loop._decide_hull(paper, four, None, None, [0, 1], 1) == (paper, None, None) and len(found) == 1


def test_the_tracking_pass_says_why_it_skips_before_it_reads_a_frame():
    """`fit.loop._track_garment`: no hull nodes, one training view, fewer than `TRACKED_NODES_MIN_VIEWS` (three views:
    the tracked tube placed synth realistic's skirt worse than the skeleton) or several processes -> one line that
    says why, 0 s, and nothing tracked (the trainer stand-in has no images, body or model to read)."""
    from types import SimpleNamespace

    from avatarctl.fit import loop

    def trainer(n_views: int, distributed: bool = False) -> SimpleNamespace:
        views = tuple(f"cam{i:02d}" for i in range(n_views))
        return SimpleNamespace(capture=SimpleNamespace(split=SimpleNamespace(train_views=views)),
                               replicas=SimpleNamespace(distributed=distributed))

    cases = ((trainer(4), 0, "no hull nodes"), (trainer(1), 8, "one training view"),
             (trainer(2), 8, "2 training views"), (trainer(3), 8, "3 training views"),
             (trainer(4, distributed=True), 8, "one process only"))
    for t, hull_count, why in cases:
        note, seconds = loop._track_garment(t, None, hull_count)
        assert note.startswith("garment tracking: skipped (") and why in note and "\n" not in note, note
        assert seconds == 0.0
    assert "4 or more" in loop._track_garment(trainer(3), None, 8)[0]
    with pytest.raises(AttributeError):  # four views, one process: the pass goes on to read the capture
        loop._track_garment(trainer(4), None, 8)
