"""The fit stage: config resolution, schedule, data sampling, the loop (files, resume, stop), checkpoints, CLI."""

from __future__ import annotations

import json
import os
import shutil
import signal
from dataclasses import replace

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from avatarctl.errors import InputError
from avatarctl.fit.config import FitConfig, parse_ablations, preset, resolve_fit_config
from avatarctl.fit.schedule import lr_at, make_optimizer, make_scheduler
from avatarctl.project import BodyModelRef, Project, SourceRef


# ---- config (no body model needed) ---------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["cpu", "paper", "micro"])
def test_config_json_round_trip(name):
    cfg = resolve_fit_config(name, ablation="no-delta-n,no-embedding", overrides=["lr=1e-4", "background=1,1,1",
                                                                                  "model.num_nodes=64"])
    back = FitConfig.from_json(json.loads(json.dumps(cfg.to_json())))
    assert back == cfg
    assert back.model.use_delta_n is False and back.model.use_embedding is False and back.model.num_nodes == 64
    assert back.background == (1.0, 1.0, 1.0) and back.lr == 1e-4 and back.ablations == ("no-delta-n", "no-embedding")


def test_paper_preset_matches_the_supplement():
    cfg = preset("paper")
    assert (cfg.rays_per_batch, cfg.images_per_batch, cfg.model.samples_per_ray, cfg.model.num_nodes) == (2048, 4, 64,
                                                                                                           128)
    assert (cfg.lr, cfg.adam_beta1, cfg.adam_beta2, cfg.lr_decay_every) == (5e-4, 0.9, 0.999, 20_000)


@pytest.mark.parametrize("overrides, needle", [
    (["lrr=1e-4"], "did you mean 'lr'"),
    (["model.num_node=3"], "model.num_nodes"),
    (["iters=ten"], "as int"),
    (["lr"], "not key=value"),
    (["ablations=no-delta-n"], "--ablation"),
    (["model.latent=banana"], "--ablation"),
    (["box_fraction=1.5"], "box_fraction"),
])
def test_bad_overrides_are_actionable_input_errors(overrides, needle):
    with pytest.raises(InputError) as e:
        resolve_fit_config("cpu", overrides=overrides)
    assert needle in e.value.one_line() and "\n" not in e.value.one_line()


def test_ablation_names_are_checked():
    assert parse_ablations("no-delta-n, lbs-baseline") == ("no-delta-n", "lbs-baseline")
    with pytest.raises(InputError, match="did you mean 'no-embedding'"):
        parse_ablations("no-embeding")
    with pytest.raises(InputError, match="both replace the latent"):
        parse_ablations("deterministic,per-frame-latent")
    cfg = resolve_fit_config("cpu", ablation="deterministic,lbs-baseline")
    assert cfg.model.latent == "deterministic" and cfg.model.variant == "lbs_baseline"


def test_presets_are_stated_once_and_the_defaults_are_the_paper():
    """One rule: `FitConfig()` / `ModelConfig()` are the paper's settings; a preset is its changes from them
    (`PRESETS`), and docs/fit.md and `--help` are made from that table."""
    from pathlib import Path

    from avatarctl.fit.presets import DEFAULT_PRESET, PRESETS, preset_help, presets_markdown
    from avatarctl.model import ModelConfig

    assert FitConfig() == preset("paper") and FitConfig().model == ModelConfig()
    assert set(PRESETS) == {"paper", "cpu", "cpu-mlp", "micro"} and DEFAULT_PRESET == "cpu"
    docs = (Path(__file__).parents[1] / "docs" / "fit.md").read_text()
    assert presets_markdown() in docs, "docs/fit.md's preset table is stale: paste presets_markdown()"
    assert all(f"'{name}'" in preset_help() for name in PRESETS)
    # the cpu preset is cpu-mlp with the Gaussian local fields, the cVAE's width decided from the capture and the
    # camera colour transforms, less the keys that do nothing for the Gaussian fields (the MLP widths, empty-space
    # skipping, the ray batch), with more, smaller garment patches, their placement corrected per frame and the lost
    # frames rescued, where it tracks a garment, and the held-out frames posed after the fit; its old name still reads
    g, c = preset("cpu"), preset("cpu-mlp")
    assert g.model.field == "gaussians" and g.model.cvae_width == "auto" and g.model.colour.enabled
    mlp_only = dict(node_width=c.model.node_width, node_depth=c.model.node_depth, feature_dim=c.model.feature_dim,
                    head_width=c.model.head_width, occupancy=c.model.occupancy)
    assert g.model.with_(field="mlp", cvae_width=c.model.cvae_width, colour=c.model.colour, hull=c.model.hull,
                         track_refine=c.model.track_refine, gaussians=c.model.gaussians, **mlp_only) == c.model
    assert g.model.gaussians == replace(c.model.gaussians, mask_border_px="auto")
    assert g.model.hull == replace(c.model.hull, tracked_nodes=256)
    assert g.model.track_refine == replace(c.model.track_refine, enabled="auto")
    assert g.track and g.track_rescue and not c.track  # garment tracking: measured with the Gaussian fields only
    assert g.held_out_poses and not c.held_out_poses  # the held-out frames posed: renders whole crops (Gaussians)
    assert replace(g, model=c.model, preset="cpu-mlp", rays_per_batch=c.rays_per_batch, track=False,
                   track_rescue=False, held_out_poses=0) == c
    assert preset("gaussians") == g
    # configs saved under the old names read as the presets' names now (the settings are the saved ones)
    assert FitConfig.from_json({**g.to_json(), "preset": "gaussians"}) == g
    assert FitConfig.from_json({**c.to_json(), "preset": "cpu"}) == c


def test_the_cvae_width_is_decided_by_the_training_views_per_frame(tmp_path):
    """`model.cvae_width = "auto"` (the cpu preset): the paper's 128 from two training views per frame on, 32 with one
    (a monocular capture); decided at fit start from the project's split, saved decided; a number is kept."""
    from fixtures.toy_capture import make_toy_capture

    from avatarctl.fit.loop import decide_auto
    from avatarctl.io.project_io import load_split, save_split
    from avatarctl.model.config import ModelConfig
    from avatarctl.model.cvae import NodeCVAE
    from avatarctl.stages import ingest
    from avatarctl.stages.fit import FitRequest, fit_config
    from avatarctl.stages.ingest import IngestConfig

    cap, proj = make_toy_capture(tmp_path / "cap"), tmp_path / "proj"
    ingest.run(proj, IngestConfig(capture=cap, project=proj))
    p = Project.open(proj)

    def width(req: FitRequest) -> int | str:
        return decide_auto(fit_config(p, req), p).model.cvae_width

    split = load_split(p.paths.split)
    assert len(split.train_views) >= 2 and fit_config(p, FitRequest()).model.cvae_width == "auto"
    assert width(FitRequest()) == 128
    assert width(FitRequest(overrides=("model.cvae_width=64",))) == 64
    assert width(FitRequest(preset="cpu-mlp")) == 32 and width(FitRequest(preset="paper")) == 128
    save_split(p.paths.split, replace(split, train_views=split.train_views[:1]))  # one camera: monocular
    assert width(FitRequest()) == 32
    assert width(FitRequest(overrides=("model.cvae_width=128",))) == 128
    with pytest.raises(ValueError, match="decided from the capture's training views"):
        NodeCVAE(ModelConfig(cvae_width="auto"), num_joints=2, num_frames=1)
    for bad in (0, "wide", True):
        with pytest.raises(ValueError, match="cvae_width must be a positive int or 'auto'"):
            ModelConfig(cvae_width=bad)


def test_nested_overrides_and_the_flat_keys_of_older_configs():
    cfg = resolve_fit_config("cpu-mlp", overrides=["model.occupancy.enabled=false", "model.pose_refine.enabled=true",
                                                   "model.hull.nodes=8"])
    m = cfg.model
    assert (m.occupancy.enabled, m.pose_refine.enabled, m.hull.nodes) == (False, True, 8)
    old = resolve_fit_config("cpu-mlp", overrides=["model.occupancy=false", "model.pose_refine=true",
                                                   "model.hull_nodes=8"])
    assert old == cfg  # the flat switch keys of older configs name the same knobs
    g = resolve_fit_config("cpu", overrides=["model.gaussians.per_node=64"])
    assert g.model.gaussians.per_node == 64
    for bad, needle in ((["model.occupancy.enabld=true"], "model.occupancy.enabled"),
                        (["model.pose_refine.enabled=maybe"], "bool or auto")):
        with pytest.raises(InputError, match=needle):
            resolve_fit_config("cpu-mlp", overrides=bad)
    with pytest.raises(TypeError, match="no truth value"):
        bool(cfg.model.occupancy)


def test_set_takes_only_the_knobs_that_act_on_the_selected_field():
    """Issue 49: a fixed setting is refused by --set (Python changes it: FitRequest.model_settings), and so is a knob
    that does nothing for the selected local fields; no preset writes such a knob; the docs' table is the code's."""
    from pathlib import Path

    from avatarctl.fit.config import config_keys, settable_keys
    from avatarctl.fit.presets import KNOBS, PRESETS, knobs_markdown

    assert len(settable_keys()) < 60 < len(config_keys())
    for bad, needle in ((["model.occupancy.res=8"], "fixed setting"), (["model.occ_res=8"], "fixed setting"),
                        (["model.gaussians.relocate_every=2"], "fixed setting"),
                        (["model.use_delta_n=false"], "--ablation no-delta-n"),
                        (["rays_per_batch=512"], "does nothing for the Gaussian fields"),
                        (["model.gaussians.per_node=8", "model.field=mlp"], "does nothing for the MLP fields")):
        with pytest.raises(InputError, match=needle) as e:
            resolve_fit_config("cpu", overrides=bad)
        assert "\n" not in e.value.one_line()
    # a knob of the other field is fine when the same command selects that field
    assert resolve_fit_config("cpu", overrides=["model.field=mlp", "rays_per_batch=256"]).rays_per_batch == 256
    for name, p in PRESETS.items():
        cfg = preset(name)
        keys = list(p.fit) + [f"model.{k}.{kk}" if isinstance(v, dict) else f"model.{k}"
                              for k, v in p.model.items() for kk in (v if isinstance(v, dict) else [None])]
        assert set(keys) <= set(KNOBS), f"preset {name} writes a fixed setting: {sorted(set(keys) - set(KNOBS))}"
        dead = [k for k in keys if KNOBS[k][0] not in ("any", cfg.model.field)]
        assert not dead, f"preset {name} writes keys that do nothing for its field: {dead}"
    assert not [k for k, (_, what) in KNOBS.items() if "|" in what], "a '|' would split the docs' table row"
    docs = (Path(__file__).parents[1] / "docs" / "fit.md").read_text()
    assert knobs_markdown() in docs, "docs/fit.md's knob table is stale: paste knobs_markdown()"


def test_config_of_schema_version_1_reads_into_the_nested_one():
    """fit/config.json as avatarctl 0081142 wrote it (flat model keys, lr_pose at the top, the switches removed in
    issue 30 at their neutral values) reads back as the same settings."""
    from pathlib import Path

    old = json.loads((Path(__file__).parent / "fixtures" / "fit_config_v1.json").read_text())
    assert old["schema_version"] == 1 and "occ_res" in old["model"] and "lr_pose" in old
    cfg = FitConfig.from_json(old)
    want = resolve_fit_config("cpu-mlp", iters=30, seed=1, overrides=["model.pose_refine.enabled=true",
                                                                      "checkpoint_every=10"])
    want = replace(want, model=want.model.with_(gaussians={"sh_degree": 1, "lambda_ssim": 0.2}))  # its saved values
    assert old["preset"] == "cpu" and cfg == want, "saved as cpu, the MLP fields' name then: read as cpu-mlp"
    assert FitConfig.from_json(json.loads(json.dumps(cfg.to_json()))) == cfg
    for key, value in (("pe_anneal_steps", 1000), ("occ_stop_eps", 1e-3)):
        with pytest.raises(InputError, match=f"{key}=.* was removed"):
            FitConfig.from_json({**old, "model": {**old["model"], key: value}})
    assert FitConfig.from_json({**old, "model": {**old["model"], "posterior_logvar_init": -6.0}}) == cfg  # init only


def test_unknown_keys_in_saved_config_are_errors():
    d = preset("micro").to_json()
    d["lerning_rate"] = 1.0
    with pytest.raises(InputError, match="lerning_rate"):
        FitConfig.from_json(d)


def test_lr_schedule_halves_every_decay_period():
    cfg = replace(preset("micro"), lr=1e-3, lr_decay_every=10, lr_decay_factor=0.5)
    p = torch.nn.Parameter(torch.zeros(1))
    opt = make_optimizer(cfg, [p])
    sched = make_scheduler(cfg, opt)
    seen = []
    for _ in range(21):
        seen.append(opt.param_groups[0]["lr"])
        opt.step()
        sched.step()
    assert seen[0] == pytest.approx(1e-3) and seen[10] == pytest.approx(5e-4) and seen[20] == pytest.approx(2.5e-4)
    assert seen[5] == pytest.approx(lr_at(cfg, 5)) and lr_at(replace(cfg, lr_decay_factor=1.0), 20) == 1e-3


def test_cli_set_typo_is_one_line_error_and_writes_nothing(tmp_path):
    from avatarctl.cli.app import app

    Project.create(tmp_path / "p", body_model=BodyModelRef("anny"), source=SourceRef("test", "synthetic", "", 0))
    res = CliRunner().invoke(app, ["fit", str(tmp_path / "p"), "--set", "itres=5"])
    assert res.exit_code == 2, res.output
    assert "unknown config key 'itres'" in res.output and "did you mean 'iters'" in res.output
    assert len(res.output.strip().splitlines()) == 1
    assert not (tmp_path / "p" / "fit").exists()


def test_sigint_sets_the_stop_flag_instead_of_raising():
    from avatarctl.fit.loop import StopFlag, _sigint_sets

    flag = StopFlag()
    with _sigint_sets(flag):
        os.kill(os.getpid(), signal.SIGINT)
        assert flag.is_set()
        with pytest.raises(KeyboardInterrupt):  # a second Ctrl-C aborts
            os.kill(os.getpid(), signal.SIGINT)


# ---- the loop on a tiny anny project -----------------------------------------------------------------------------
@pytest.fixture(scope="module")
def tiny_project_dir(tmp_path_factory):
    from fixtures.tiny_project import make_tiny_project

    root = tmp_path_factory.mktemp("fit") / "tiny"
    make_tiny_project(root, size=32, frames=3, cams=4)
    return root


@pytest.fixture
def project(tiny_project_dir, tmp_path):
    dest = tmp_path / "proj"
    shutil.copytree(tiny_project_dir, dest)
    return Project.open(dest)


def _cfg(**kw) -> FitConfig:
    base = dict(iters=6, log_every=2, checkpoint_every=3, val_every=3, val_pairs=2, rays_per_batch=64,
                images_per_batch=2, seed=3)
    base.update(kw)
    return replace(preset("micro"), **base)


@pytest.mark.anny
def test_fit_writes_checkpoints_log_config_and_stage_record(project):
    from avatarctl.fit.checkpoint import read_checkpoint
    from avatarctl.fit.loop import decide_auto, fit

    cfg = _cfg()
    res = fit(project, cfg, device="cpu")
    p = project.paths
    assert res.step == 6 and not res.interrupted and res.checkpoint == p.checkpoint(6)
    assert p.checkpoint(3).is_file() and p.checkpoint(6).is_file() and p.latest_checkpoint.is_file()
    ckpt = torch.load(p.latest_checkpoint, weights_only=True)  # plain tensors / JSON values only
    assert ckpt["step"] == 6 and ckpt["train_frames"] == [0, 1, 2]
    # the config as trained: micro's "auto" pose refinement decided (on: this capture's fits are not ground truth)
    assert cfg.model.pose_refine.enabled == "auto" and res.config.model.pose_refine.enabled is True
    assert res.config == decide_auto(cfg, project)
    assert FitConfig.from_json(ckpt["fit_config"]) == res.config
    assert read_checkpoint(p.latest_checkpoint)["model_config"] == res.config.model.to_json()
    assert FitConfig.from_json(json.loads(p.fit_config.read_text())) == res.config
    records = [json.loads(line) for line in p.fit_log.read_text().splitlines()]
    assert [r["step"] for r in records if "loss" in r] == [2, 4, 6]
    assert all(np.isfinite(r["loss"]["total"]) for r in records if "loss" in r)
    vals = [r["val"]["psnr"] for r in records if "val" in r]
    assert len(vals) == 2 and all(np.isfinite(v) and v > 0 for v in vals)
    rec = Project.open(project.root).require("fit")
    assert rec.summary["step"] == 6 and rec.summary["interrupted"] is False
    assert rec.summary["val_psnr_bbox"] == pytest.approx(vals[-1])
    assert not list(p.checkpoints.glob(".*tmp*"))  # nothing half-written left behind


@pytest.mark.anny
def test_resume_equals_straight_run_bitwise(project, tmp_path):
    from avatarctl.fit.loop import fit

    other = Project.open(shutil.copytree(project.root, tmp_path / "other"))
    cfg = _cfg(checkpoint_every=100)
    straight = fit(project, cfg, device="cpu")
    half = fit(other, replace(cfg, iters=3), device="cpu")
    assert half.step == 3
    with pytest.raises(InputError, match="differs from the checkpoint"):
        fit(other, replace(cfg, lr=1e-3), device="cpu", resume=True)
    resumed = fit(other, cfg, device="cpu", resume=True)
    assert straight.step == resumed.step == 6
    a = torch.load(straight.checkpoint, weights_only=True)
    b = torch.load(resumed.checkpoint, weights_only=True)
    for k in a["model"]:
        assert torch.equal(a["model"][k], b["model"][k]), k
    for k, st in a["optimizer"]["state"].items():
        for name, v in st.items():
            assert torch.equal(torch.as_tensor(v), torch.as_tensor(b["optimizer"]["state"][k][name])), (k, name)
    assert a["scheduler"]["last_epoch"] == b["scheduler"]["last_epoch"] == 6
    assert straight.losses == resumed.losses


@pytest.mark.anny
def test_stop_saves_a_checkpoint_and_resume_finishes(project):
    from avatarctl.fit.loop import StopFlag, fit

    stop = StopFlag()

    def progress(rep):
        if rep.step == 1:
            stop.set()  # what the first Ctrl-C does

    res = fit(project, _cfg(), device="cpu", progress=progress, stop=stop)
    assert res.interrupted and res.step == 1 and res.checkpoint == project.paths.checkpoint(1)
    assert np.isfinite(res.losses["total"])  # the last step's losses, though step 1 is not a log step
    assert torch.load(project.paths.latest_checkpoint, weights_only=True)["step"] == 1
    assert Project.open(project.root).last("fit").summary["stop_reason"] == "interrupted"
    with pytest.raises(Exception, match="already has a fit"):
        fit(project, _cfg(), device="cpu")
    done = fit(project, None, device="cpu", resume=True)
    assert done.step == 6 and not done.interrupted


@pytest.mark.anny
def test_load_avatar_round_trip_and_conditioning(project):
    from avatarctl.fit.checkpoint import load_avatar
    from avatarctl.fit.loop import fit
    from avatarctl.render.engine import render_view

    cfg = _cfg(iters=2, val_pairs=0)
    res = fit(project, cfg, device="cpu")
    av = load_avatar(project)
    ckpt = torch.load(project.paths.latest_checkpoint, weights_only=True)
    assert av.step == 2 and av.train_frames == [0, 1, 2] and av.model_config == res.config.model
    assert av.background == (0.0, 0.0, 0.0) and not av.model.training
    for k, v in ckpt["model"].items():
        assert torch.equal(av.model.state_dict()[k], v), k
    motion = av.capture.motion
    cond = av.conditioning(motion.select([1, 2]), frames_are_training=True)
    assert torch.allclose(cond.time, torch.tensor([1 / 3, 2 / 3])) and cond.frame_ids.tolist() == [1, 2]
    novel = av.conditioning(motion.select([1]), frames_are_training=False)
    assert novel.frame_ids.tolist() == [-1] and novel.time.tolist() == [0.0]
    state = av.model.node_state(cond, mode="mean")
    cam = av.capture.cameras["cam01"]
    view = render_view(av.model, state, 0, cam, av.background)
    assert view.rgb.shape == (32, 32, 3) and np.isfinite(view.rgb).all() and view.rays > 0
    with pytest.raises(Exception, match="checkpoint not found"):
        load_avatar(project, checkpoint=project.paths.checkpoint(999))


@pytest.mark.anny
def test_ray_sampler_targets_and_box_fraction(project):
    from avatarctl.body.registry import load_body_model
    from avatarctl.fit.conditioning import build_pose_table
    from avatarctl.fit.data import FrameStore, RaySampler
    from avatarctl.io.project_io import load_project_capture

    cap = load_project_capture(project)
    body = load_body_model("anny")
    poses = build_pose_table(body, cap.motion, [0, 1, 2])
    store = FrameStore(cap, poses, crop_pad=0.1, budget_bytes=1)  # budget below one crop: keeps only the newest
    sampler = RaySampler(store, [0, 1, 2], ["cam00", "cam02"], rays_per_batch=400, images_per_batch=1,
                         box_fraction=0.9, background=(0.2, 0.4, 0.6))
    batch = sampler.sample(torch.Generator().manual_seed(0))
    assert batch.rays.origins.shape == (400, 3) and batch.target.shape == (400, 3) and len(store) == 1
    cam = cap.cameras[batch.views[0]]
    crop = store.get(batch.views[0], batch.frames[0])
    # recover the pixels from the rays and check the targets against the image composited over the background
    pts = batch.rays.origins + batch.rays.dirs
    uv = np.round(cam.project(pts.double().numpy(), distort=False)).astype(int)
    img = cap.image(cam.name, batch.frames[0]).astype(np.float32) / 255
    m = cap.mask(cam.name, batch.frames[0]).astype(np.float32)[..., None]
    gt = (img * m + np.array([0.2, 0.4, 0.6], np.float32) * (1 - m))[uv[:, 1], uv[:, 0]]
    h, w = crop.mask.shape
    in_crop = (uv[:, 0] >= crop.x0) & (uv[:, 0] < crop.x0 + w) & (uv[:, 1] >= crop.y0) & (uv[:, 1] < crop.y0 + h)
    np.testing.assert_allclose(batch.target.numpy()[in_crop], gt[in_crop], atol=1e-6)
    box = np.zeros((cam.height, cam.width), bool)
    box[crop.y0 + crop.inside // w, crop.x0 + crop.inside % w] = True
    assert box[uv[:360, 1], uv[:360, 0]].all()  # the first 90% are inside the projected box
    assert batch.cond.time.tolist() == pytest.approx([batch.frames[0] / 3])
    again = sampler.sample(torch.Generator().manual_seed(0))
    assert torch.equal(again.target, batch.target) and torch.equal(again.rays.dirs, batch.rays.dirs)


@pytest.mark.anny
def test_cli_fit_runs_and_resumes(project):
    from avatarctl.cli.app import app

    runner = CliRunner()
    res = runner.invoke(app, ["fit", str(project.root), "--preset", "micro", "--iters", "2", "--device", "cpu",
                              "--set", "rays_per_batch=32", "--set", "val_pairs=1", "--ablation", "no-delta-n"])
    assert res.exit_code == 0, res.output
    assert "held-out PSNR (bbox)" in res.output and "2 / 2" in res.output
    cfg = FitConfig.from_json(json.loads(project.paths.fit_config.read_text()))
    assert cfg.rays_per_batch == 32 and cfg.model.use_delta_n is False and cfg.ablations == ("no-delta-n",)
    res = runner.invoke(app, ["fit", str(project.root), "--resume", "--seed", "4"])
    assert res.exit_code == 2 and "--seed cannot change a fit being resumed" in res.output
    res = runner.invoke(app, ["fit", str(project.root), "--resume", "--iters", "3", "--device", "cpu"])
    assert res.exit_code == 0, res.output
    assert torch.load(project.paths.latest_checkpoint, weights_only=True)["step"] == 3


@pytest.mark.anny
def test_time_budget_stops_with_checkpoint_and_validation(project):
    from avatarctl.fit.loop import fit

    res = fit(project, _cfg(iters=1000, time_budget_s=1e-9), device="cpu")
    assert res.stop_reason == "time_budget" and not res.interrupted and res.step == 0
    assert res.val is not None and np.isfinite(res.val.psnr)  # still validated
    assert torch.load(project.paths.latest_checkpoint, weights_only=True)["step"] == 0


def test_a_chain_passes_typed_settings_not_strings(tmp_path):
    """demo / reproduce set FitConfig values as typed `FitRequest.settings` (no "time_budget_s=…" string parsed
    back); they give what the same `--set` strings give, and a resumed fit refuses them like `--set`."""
    from fixtures.toy_capture import make_toy_project

    from avatarctl.stages.fit import FitRequest, fit_config

    _, proj = make_toy_project(tmp_path)
    p = Project.open(proj)
    typed = fit_config(p, FitRequest(preset="micro", settings={"time_budget_s": 12.5, "val_every": 0}))
    assert typed.time_budget_s == 12.5 and typed.val_every == 0
    assert typed == fit_config(p, FitRequest(preset="micro", overrides=("time_budget_s=12.5", "val_every=0")))
    with pytest.raises(InputError, match="--set cannot change a fit being resumed"):
        fit_config(p, FitRequest(resume=True, settings={"val_every": 0}))
