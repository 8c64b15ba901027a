"""The fit stage: `fit(project, cfg)` trains an `SlrfAvatar` on the project's training views and frames.

One step (paper Sec. 4, supplement): draw a `TrainBatch` (data.py), compute the node state with the posterior
latent (z ~ N(mu, sigma), reparameterised), render the rays (uniform samples, jittered), the loss of Eq. 11
(`model.losses`), Adam step, lr schedule step. Every `log_every` steps a record goes to `fit/log.jsonl`, every
`val_every` steps a held-out-view validation (validate.py), every `checkpoint_every` steps and at the end a
checkpoint (checkpoint.py). The stage is recorded in the project manifest at the end (also when interrupted).

Reproducibility: the model is initialised from `cfg.seed`; the ray sampler and the model noise (latent samples,
sample jitter) use their own `torch.Generator`s whose states are checkpointed with the global torch RNG, the
optimiser and the scheduler, so N steps straight and N/2 + `resume` N/2 give the same parameters (bitwise on CPU
in our test).

Interruption: Ctrl-C (SIGINT, first press) or `StopFlag.set()` ends the run after the current step with a
checkpoint; a second Ctrl-C aborts immediately. `FitConfig.time_budget_s` ends a run the same way after that many
seconds of training, but still validates (stop_reason "time_budget").

Several ranks (`env`, `avatarctl.dist`): data-parallel over ray shards (fit/distributed.py: `Replicas` samples,
renders and synchronises); rank 0 alone writes the config, log, checkpoints and project record and validates; the
ranks stop after the same step (docs/distributed.md).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import signal
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Iterator

import torch

from avatarctl.atomic import remove_stale_temps, write_json, write_text
from avatarctl.device import resolve_device
from avatarctl.dist import rank_device
from avatarctl.errors import AvatarError, InputError, ProjectError
from avatarctl.fit.config import MASK_DILATE_PX, FitConfig, config_summary
from avatarctl.model.config import AUTO, ModelConfig
from avatarctl.project import Project, now_iso

if TYPE_CHECKING:
    from avatarctl.dist import DistEnv
    from avatarctl.fit.distributed import Replicas
    from avatarctl.fit.hull_nodes import HullNodes
    from avatarctl.fit.refined import RefinementSummary
    from avatarctl.fit.validate import ValidationResult


class StopFlag:
    """Ask a running `fit` to stop after the current step (what Ctrl-C does)."""

    def __init__(self, event: Any = None) -> None:
        self._event = event if event is not None else threading.Event()  # or a multiprocessing Event

    def set(self) -> None:
        self._event.set()

    def is_set(self) -> bool:
        return self._event.is_set()


@dataclass(frozen=True)
class StepReport:
    """Sent to the progress callback after every step."""

    step: int  # steps completed
    iters: int  # target step count
    start_step: int  # step this run started from (resume)
    losses: dict[str, float]  # latest logged loss terms (updated every `log_every` steps)
    lr: float
    rays_per_s: float  # over the latest log window
    val_psnr: float | None  # latest validation PSNR (bbox, dB)


@dataclass(frozen=True)
class FitResult:
    step: int
    iters: int
    interrupted: bool  # stopped by Ctrl-C / StopFlag before `iters`
    stop_reason: str  # "done" | "interrupted" | "time_budget"
    checkpoint: Path
    seconds: float  # wall time of this run (excluding set-up)
    setup_seconds: float
    losses: dict[str, float]
    val: "ValidationResult | None"  # latest validation (fit/validate.py)
    rays_per_s: float
    device: str
    config: FitConfig
    refinement: "RefinementSummary | None" = None  # pose refinement on: how far it moved the fits (fit/refined.py)
    hull_nodes: str | None = None  # model.hull_nodes on (a fresh fit): what the masks showed, how many nodes it placed


@contextlib.contextmanager
def _sigint_sets(flag: StopFlag) -> Iterator[None]:
    """While inside: the first SIGINT sets `flag`, a second raises KeyboardInterrupt. Main thread only."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):  # noqa: ARG001
        if flag.is_set():
            raise KeyboardInterrupt
        flag.set()

    previous = signal.signal(signal.SIGINT, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def _read_log(path: Path, upto_step: int) -> list[str]:
    """Log lines with step <= upto_step (a torn last line is dropped)."""
    if not path.is_file():
        return []
    keep = []
    for line in path.read_text().splitlines():
        try:
            if json.loads(line)["step"] <= upto_step:
                keep.append(line)
        except (json.JSONDecodeError, KeyError, TypeError):
            continue
    return keep


class _Log:
    """fit/log.jsonl: one JSON object per line, each appended with a single write + fsync."""

    def __init__(self, path: Path, keep_lines: list[str]):
        self.path = path
        write_text(path, "".join(line + "\n" for line in keep_lines))  # atomic rewrite (drops records past resume)

    def append(self, record: dict[str, Any]) -> None:
        data = (json.dumps(record) + "\n").encode()
        fd = os.open(self.path, os.O_WRONLY | os.O_APPEND)
        try:
            os.write(fd, data)
            os.fsync(fd)
        finally:
            os.close(fd)


def _val_record(val: "ValidationResult") -> dict[str, Any]:
    """The log's view of a validation result."""
    d = val.to_json()
    return {"psnr": d["psnr"], "pairs": d["pairs"], "protocol": d["protocol"], "scale": d["scale"],
            "seconds": round(d["seconds"], 2)}


def _rng_state(replicas: "Replicas") -> dict[str, Any]:
    return {"torch": torch.get_rng_state(), "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else [],
            **replicas.rng_state()}


def _set_rng_state(rng: dict[str, Any]) -> None:
    torch.set_rng_state(rng["torch"].cpu())
    if rng.get("cuda") and torch.cuda.is_available():
        torch.cuda.set_rng_state_all([s.cpu() for s in rng["cuda"]])


def _resume_config(cfg: FitConfig | None, saved: FitConfig) -> FitConfig:
    """On resume the saved config holds; only `iters` may change."""
    if cfg is None:
        return saved
    if replace(cfg, iters=saved.iters) != saved:
        a, b = cfg.to_json(), saved.to_json()
        diff = sorted(k for k in a if a[k] != b.get(k) and k != "iters")
        if "model" in diff:
            diff.remove("model")
            diff += sorted(f"model.{k}" for k in a["model"] if a["model"][k] != b["model"].get(k))
        raise InputError(f"--resume with a config that differs from the checkpoint's ({', '.join(diff)})",
                         fix="resume without --preset/--set/--ablation/--seed (only --iters may change), "
                             "or start over with --fresh")
    return cfg


def _place_hull_nodes(model_cfg: ModelConfig, seed: int, capture, body, template, train_frames: list[int],
                      views: list[str]) -> "tuple[HullNodes | None, str]":
    """`model.hull.nodes` = K or "auto" (fit/hull_nodes.py): survey the training masks, decide K for "auto", place
    the nodes. -> (the K hull nodes, or None for the paper's placement; the line for the log and the summary)."""
    from avatarctl.fit.hull_nodes import auto_hull_nodes, choose_hull_nodes, survey_hull
    from avatarctl.model.deformer import farthest_point_sampling

    opts = model_cfg.hull
    N, auto = model_cfg.num_nodes, opts.nodes == AUTO
    k = model_cfg.hull_auto_nodes if auto else int(opts.nodes)
    surface = farthest_point_sampling(template.vertices, N - k, seed)
    survey = survey_hull(capture, body, template, train_frames, views, surface, opts.min_dist)
    if auto:
        k = auto_hull_nodes(survey, k, opts.auto_min_volume)
        if not k:
            return None, (f"hull: {survey.describe()} < {100 * opts.auto_min_volume:g} % -> none "
                          f"(hull_nodes=auto: all {N} nodes on the surface)")
    hull = choose_hull_nodes(survey, template, template.vertices.detach().float()[surface], k)
    more = f", {k - hull.off_body} more on the surface" if hull.off_body < k else ""
    why = f" >= {100 * opts.auto_min_volume:g} % (hull_nodes=auto)" if auto else ""
    return hull, f"hull: {survey.describe()}{why} -> {hull.off_body} of {N} nodes placed off the body{more}"


def decide_auto(cfg: FitConfig, project: Project) -> FitConfig:
    """`cfg` with `model.pose_refine.enabled = "auto"` decided from the project's capture: on when its body fits are
    not ground truth (real captures, synth with --fit-noise). The saved config holds the decision."""
    refine = cfg.model.pose_refine
    if refine.enabled != AUTO:
        return cfg
    from avatarctl.io.gt_geometry import fits_are_ground_truth

    decided = refine.resolved(fits_are_ground_truth(project.manifest.source.path))
    return replace(cfg, model=cfg.model.with_(pose_refine=decided))


def fit(project: Project, cfg: FitConfig | None = None, *, device: str = "auto", resume: bool = False,
        fresh: bool = False, progress: Callable[[StepReport], None] | None = None, stop: StopFlag | None = None,
        handle_sigint: bool = True, env: "DistEnv | None" = None, shards: int | None = None) -> FitResult:
    """Train (or resume training) the project's avatar; see the module docstring. `cfg` may be None on resume.
    `env`: this process's rank in a started group (None: one process); `shards`: ray shards (fit/distributed.py;
    None = the world size for a fresh fit, the checkpoint's on resume when the world size divides them)."""
    from avatarctl.body.registry import load_body_model
    from avatarctl.fit.checkpoint import read_checkpoint, save_checkpoint, save_snapshot
    from avatarctl.fit.conditioning import build_pose_table, make_conditioning, time_stamps
    from avatarctl.fit.data import FrameStore, ImageSampler, RaySampler
    from avatarctl.fit.distributed import Replicas, saved_shards
    from avatarctl.fit.schedule import make_optimizer, make_scheduler, param_groups
    from avatarctl.fit.validate import Validator, choose_val_pairs
    from avatarctl.io.project_io import load_project_capture
    from avatarctl.model.avatar import SlrfAvatar

    t_setup = time.perf_counter()
    started = now_iso()
    paths = project.paths
    dev = rank_device(env, resolve_device(device))
    main = env is None or env.is_main
    capture = load_project_capture(project)
    split = capture.split
    if not split.train_frames or not split.train_views:
        raise ProjectError("the project's split has no training frames or views", where=str(paths.split),
                           fix="re-run `avatarctl ingest` with training frames/views")
    for v in list(split.train_views) + list(split.test_views):
        if v not in capture.cameras:
            raise ProjectError(f"split names camera {v!r} that is not in cameras.json", where=str(paths.split),
                               fix="re-run `avatarctl ingest`")
    train_frames = sorted(int(f) for f in split.train_frames)
    if cfg is not None:
        cfg = decide_auto(cfg, project)
    ckpt = None
    if resume:
        ckpt = read_checkpoint(paths.latest_checkpoint)
        cfg = _resume_config(cfg, FitConfig.from_json(ckpt["fit_config"]))
        if [int(f) for f in ckpt["train_frames"]] != train_frames:
            raise ProjectError("the checkpoint was trained on other frames than the project's split",
                               where=str(paths.latest_checkpoint), fix="start over with --fresh")
    else:
        if cfg is None:
            raise ValueError("fit() needs a FitConfig unless resume=True")
        if paths.latest_checkpoint.exists() and not fresh:
            raise ProjectError("this project already has a fit", where=str(paths.fit),
                               fix="pass --resume to continue it, or --fresh to discard it and start over")
        if fresh and main:
            for p in list(paths.checkpoints.glob("*.pt")) + [paths.fit_log]:
                p.unlink(missing_ok=True)
    assert cfg is not None
    remove_stale_temps(paths.checkpoints)  # torn writes of a killed run (never `latest.pt` itself: renames are atomic)
    start_step = int(ckpt["step"]) if ckpt is not None else 0
    world = env.world_size if env is not None else 1
    if shards is None:
        shards = world if ckpt is None else saved_shards(ckpt["rng"])
        shards = shards if shards % world == 0 else world
    if main:
        write_json(paths.fit_config, cfg.to_json())

    body = load_body_model(capture.body_model, capture.body_model_path)
    template = body.template(capture.motion)
    poses = build_pose_table(body, capture.motion, train_frames)
    store = FrameStore(capture, poses, cfg.crop_pad, cfg.cache_mb * 2**20, MASK_DILATE_PX)
    # the ray-marched fields learn from scattered rays, the rasterized one (model.field = "gaussians") from whole crops
    Sampler = RaySampler if cfg.model.ray_marched else ImageSampler
    replicas = Replicas(env, shards, lambda pairs, rays, images: Sampler(
        store, train_frames, split.train_views, rays, images, cfg.box_fraction, cfg.background, cfg.mask_fraction,
        pairs), train_frames, list(split.train_views), cfg.rays_per_batch, cfg.images_per_batch, cfg.seed, dev)
    pairs = choose_val_pairs(split.test_views, train_frames, cfg.val_pairs) if main else []
    validator = Validator(capture, body, pairs, train_frames, cfg.background, cfg.val_scale) if pairs else None

    hull, hull_note = None, None
    if cfg.model.hull.on and cfg.model.variant == "slrf" and ckpt is None:  # nodes off the body (fit/hull_nodes.py)
        hull, hull_note = _place_hull_nodes(cfg.model, cfg.seed, capture, body, template, train_frames,
                                            list(split.train_views))
    with torch.random.fork_rng(devices=[]):  # weights initialised from cfg.seed, global RNG left as it was
        torch.manual_seed(cfg.seed)
        model = SlrfAvatar(cfg.model, template, num_frames=len(train_frames), seed=cfg.seed,
                           hull_nodes=None if hull is None else (hull.rest, hull.vertex),
                           off_body=None if hull is None else (torch.from_numpy(hull.survey.cells), hull.survey.cell)
                           ).to(dev)
    if model.pose_refine is not None and ckpt is None:  # canonical joint centres from the training poses
        from avatarctl.body.joints import joint_centres, skin_weighted_centroids

        model.pose_refine.set_centres(joint_centres(poses.joint_transforms, template.parents,
                                                    skin_weighted_centroids(template.vertices, template.skin_weights)))
    if model.pose_refine is not None and cfg.model.pose_refine.lambda_accel > 0:  # the sequence the smoothness sees
        model.pose_refine.set_sequence(poses.joint_transforms, train_frames, capture.motion.fps)
    model.train()
    optimizer = make_optimizer(cfg, param_groups(cfg, model))
    relocate_every = 0 if cfg.model.ray_marched else cfg.model.gaussians.relocate_every
    if relocate_every:
        from avatarctl.fit.densify import relocate_dead
    scheduler = make_scheduler(cfg, optimizer)
    if ckpt is not None:
        model.load_state_dict(ckpt["model"])
        optimizer.load_state_dict(ckpt["optimizer"])
        scheduler.load_state_dict(ckpt["scheduler"])
        _set_rng_state(ckpt["rng"])
        same_stream = replicas.load_rng_state(ckpt["rng"], cfg.seed, start_step)
    log = _Log(paths.fit_log, _read_log(paths.fit_log, start_step) if resume else []) if main else None
    if hull_note is not None and log is not None:
        log.append({"step": 0, "note": hull_note})
    if ckpt is not None and not same_stream and log is not None:
        log.append({"step": start_step, "note": f"resumed on {world} ranks: {saved_shards(ckpt['rng'])} ray shards "
                                                f"resharded to {shards}, new sampling streams"})
    background = torch.tensor(cfg.background, dtype=torch.float32, device=dev)
    use_amp = cfg.amp and dev.type == "cuda"
    stop = stop or StopFlag()

    all_frames = make_conditioning(poses.joint_transforms, poses.pose_features,
                                   *time_stamps(train_frames, train_frames, True), device=dev)

    def payload(step: int) -> dict[str, Any]:
        model.set_latent_mean(all_frames)  # model.novel_latent = "train_mean": z of novel poses (model/cvae.py)
        return {"step": step, "model": model.state_dict(), "optimizer": optimizer.state_dict(),
                "scheduler": scheduler.state_dict(), "rng": _rng_state(replicas),
                "model_config": cfg.model.to_json(), "fit_config": cfg.to_json(), "train_frames": train_frames}

    def checkpoint(step: int) -> Path:  # every rank (the shards' generator states are gathered), rank 0 writes
        data = payload(step)
        return save_checkpoint(project, data, keep=cfg.keep_checkpoints) if main else paths.checkpoint(step)

    snapshots = list(cfg.snapshot_at_s)

    setup_seconds = time.perf_counter() - t_setup
    step = start_step
    losses: dict[str, float] = {}
    val: ValidationResult | None = None
    last_ckpt: Path | None = paths.latest_checkpoint if ckpt is not None else None
    saved_step = start_step if ckpt is not None else -1
    window_t, window_rays, rays_per_s = time.perf_counter(), 0, 0.0
    t_run = time.perf_counter()
    sig = _sigint_sets(stop) if handle_sigint else contextlib.nullcontext()
    with sig:
        budget_hit = agreed_stop = False  # several ranks stop on the flags they agreed on, never on a local one
        while step < cfg.iters and not (agreed_stop if replicas.distributed else stop.is_set()):
            if not replicas.distributed and cfg.time_budget_s and time.perf_counter() - t_run >= cfg.time_budget_s:
                budget_hit = True
                break
            occ_start = replicas.begin_step(model)
            with torch.autocast(device_type="cuda", dtype=torch.bfloat16) if use_amp else contextlib.nullcontext():
                terms, out, step_rays = replicas.forward(model, background, cfg.jitter)
            optimizer.zero_grad(set_to_none=True)
            terms.total.backward()
            elapsed = time.perf_counter() - t_run
            agreed = replicas.sync(model, terms, occ_start, stop=stop.is_set(),
                                   budget=main and bool(cfg.time_budget_s) and elapsed >= cfg.time_budget_s,
                                   snapshot=main and bool(snapshots) and elapsed >= snapshots[0])
            if cfg.grad_clip > 0:
                torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip)
            optimizer.step()
            scheduler.step()
            step += 1
            if relocate_every and step % relocate_every == 0:  # the Gaussians' density control (fit/densify.py)
                relocate_dead(model.fields, optimizer, cfg.model.gaussians.min_opacity, cfg.seed, step)
            window_rays += step_rays

            record: dict[str, Any] = {}
            if step % cfg.log_every == 0 or step == cfg.iters:
                losses = agreed.losses or terms.as_floats()
                if not all(math.isfinite(v) for v in losses.values()):
                    raise AvatarError(f"training diverged: non-finite loss at step {step} ({losses})",
                                      where=str(paths.fit),
                                      fix="resume from the last checkpoint with a lower lr (--fresh --set lr=...)")
                now = time.perf_counter()
                rays_per_s = window_rays / max(now - window_t, 1e-9)
                window_t, window_rays = now, 0
                record = {"lr": optimizer.param_groups[0]["lr"], "loss": losses, "rays_per_s": round(rays_per_s, 1),
                          "cache": {"images": len(store), "mb": round(store.cached_bytes / 2**20, 1),
                                    "hits": store.hits, "misses": store.misses},
                          "stats": {k: float(v) for k, v in out.stats.items()}}
            if validator is not None and cfg.val_every and step % cfg.val_every == 0:
                val = validator.score(model)
                record["val"] = _val_record(val)
            if record and log is not None:
                log.append({"step": step, "time": round(time.perf_counter() - t_run, 3), **record})
            if step % cfg.checkpoint_every == 0:
                last_ckpt, saved_step = checkpoint(step), step
            while snapshots and (agreed.snapshot if replicas.distributed else
                                 time.perf_counter() - t_run >= snapshots[0]):
                data = payload(step)
                if main:
                    save_snapshot(project, data, snapshots[0])
                snapshots.pop(0)
                agreed = replace(agreed, snapshot=False)
            if progress is not None:
                progress(StepReport(step=step, iters=cfg.iters, start_step=start_step, losses=losses,
                                    lr=optimizer.param_groups[0]["lr"], rays_per_s=rays_per_s,
                                    val_psnr=None if val is None else val.psnr))
            if agreed.stop:
                agreed_stop = True
            if agreed.budget:
                budget_hit = True
                break
    seconds = time.perf_counter() - t_run
    if step > start_step and step % cfg.log_every:  # stopped between log steps: report the last step's losses
        losses = agreed.losses or terms.as_floats()
    interrupted = step < cfg.iters and not budget_hit
    stop_reason = "interrupted" if interrupted else ("time_budget" if budget_hit else "done")
    if saved_step != step:
        last_ckpt = checkpoint(step)
    if validator is not None and not interrupted and (val is None or not cfg.val_every or step % cfg.val_every):
        val = validator.score(model)
        assert log is not None
        log.append({"step": step, "time": round(time.perf_counter() - t_run, 3), "val": _val_record(val)})
    assert last_ckpt is not None
    refinement = None
    if main and model.pose_refine is not None:  # the refined fits as a motion file (fit/refined.py)
        from avatarctl.fit.refined import write_refined_fits

        refinement = write_refined_fits(paths.fit, body, capture.motion, poses, model.pose_refine)
    summary = {"step": step, "iters": cfg.iters, "start_step": start_step, "interrupted": interrupted,
               "stop_reason": stop_reason,
               "seconds": round(seconds, 2), "setup_seconds": round(setup_seconds, 2), "losses": losses,
               "rays_per_s": round(rays_per_s, 1), "device": str(dev),
               "val_psnr_bbox": None if val is None else val.psnr,
               "val_pairs": None if val is None else val.to_json()["pairs"], "ranks": world, "ray_shards": shards,
               "pose_refinement": None if refinement is None else refinement.to_json(), "hull_nodes": hull_note,
               **config_summary(cfg)}
    if main:
        project.record("fit", {"fit": cfg.to_json(), "device": str(dev), "resume": resume, "ranks": world,
                               "ray_shards": shards},
                       [paths.fit_config, paths.fit_log, paths.latest_checkpoint]
                       + ([refinement.path] if refinement is not None and refinement.path else []), started, summary)
    return FitResult(step=step, iters=cfg.iters, interrupted=interrupted, stop_reason=stop_reason,
                     checkpoint=last_ckpt, seconds=seconds,
                     setup_seconds=setup_seconds, losses=losses, val=val, rays_per_s=rays_per_s, device=str(dev),
                     config=cfg, refinement=refinement, hull_nodes=hull_note)
