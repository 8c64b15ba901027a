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

The file reads in the order of a run: `_set_up` (`_open_run`: split checks, resume or fresh, `decide_auto`; the data,
`_build_model`, optimiser, log), `_train_step` (one optimisation step), `_Books.after_step` (log, validation,
checkpoints, snapshots, progress), the stop rule in `fit`, and `_finish` (last checkpoint, final validation, refined
fits, project record).

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

from avatarctl.atomic import atomic_path, remove_stale_temps, write_json, write_text
from avatarctl.device import resolve_device
from avatarctl.dist import rank_device
from avatarctl.errors import AvatarError, InputError, ProjectError
from avatarctl.fit.config import FitConfig, config_summary
from avatarctl.model.config import AUTO, ModelConfig
from avatarctl.project import Project, now_iso

if TYPE_CHECKING:
    from avatarctl.dist import DistEnv
    from avatarctl.fit.distributed import Replicas, StepSync
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
    garment_tracking: str | None = None  # `track` on (a fresh fit): what the tracking pass did, or why it did not run
    held_out_poses: dict[str, Any] | None = None  # `held_out_poses` on: what posing the held-out frames did, or why not


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
    """`cfg` with the "auto" values of the model decided from the project's capture (the saved config holds the
    decisions): `model.pose_refine.enabled` on when its body fits are not ground truth (real captures, synth with
    --fit-noise); `model.gaussians.mask_border_px` 1 when its masks are not ground truth (estimated by ingest, or a real
    capture's) and each frame has two training views or more; `model.cvae_width` from the number of training views of
    each frame (`ModelConfig.with_cvae_width_for`). `model.hull.nodes` is decided later, from the masks
    (`_place_hull_nodes`)."""
    from avatarctl.io.project_io import load_split

    model = cfg.model
    train_views = len(load_split(project.paths.split).train_views) \
        if AUTO in (model.gaussians.mask_border_px, model.cvae_width) else 0
    if model.pose_refine.enabled == AUTO:
        from avatarctl.io.gt_geometry import fits_are_ground_truth

        model = model.with_(pose_refine=model.pose_refine.resolved(
            fits_are_ground_truth(project.manifest.source.path)))
    if model.gaussians.mask_border_px == AUTO:
        from avatarctl.io.gt_geometry import masks_are_ground_truth

        ingest = project.last("ingest")
        masks = ingest.config.get("resolved", {}).get("masks") if ingest is not None else None
        model = model.with_(gaussians=model.gaussians.resolved(masks_are_ground_truth(
            project.manifest.source.path, masks), train_views))
    if model.cvae_width == AUTO:
        model = model.with_cvae_width_for(train_views)
    return cfg if model is cfg.model else replace(cfg, model=model)


# ---- set-up ------------------------------------------------------------------------------------------------------
@dataclass
class _Trainer:
    """Everything set-up builds and every step uses: the data, the model and its optimiser, the ranks."""

    project: Project
    cfg: FitConfig
    dev: torch.device
    env: "DistEnv | None"
    shards: int
    capture: Any  # ProjectCapture
    body: Any  # BodyModel
    template: Any  # BodyTemplate of the capture's body
    poses: Any  # PoseTable of the training frames
    train_frames: list[int]
    store: Any  # FrameStore (the cache the log reports)
    replicas: "Replicas"
    validator: "Any | None"  # Validator, None without held-out views (and on ranks > 0)
    model: Any  # SlrfAvatar
    optimizer: torch.optim.Optimizer
    scheduler: Any
    background: torch.Tensor  # [3]
    all_frames: Any  # FrameConditioning of every training frame (the novel-pose latent's mean)
    start_step: int
    resumed: bool
    hull_note: str | None  # what the hull survey decided (fresh fits with model.hull on)
    track_note: str | None = None  # what the garment tracking pass did, or why it did not run (fresh fits, `track`)
    track_seconds: float = 0.0  # its time (counted towards time_budget_s)

    @property
    def main(self) -> bool:
        return self.env is None or self.env.is_main

    @property
    def world(self) -> int:
        return self.env.world_size if self.env is not None else 1

    def payload(self, step: int) -> dict[str, Any]:
        """A checkpoint's contents at `step` (every rank: the shards' generator states are gathered)."""
        self.model.set_latent_mean(self.all_frames)  # model.novel_latent = "train_mean": z of novel poses
        return {"step": step, "model": self.model.state_dict(), "optimizer": self.optimizer.state_dict(),
                "scheduler": self.scheduler.state_dict(), "rng": _rng_state(self.replicas),
                "model_config": self.cfg.model.to_json(), "fit_config": self.cfg.to_json(),
                "train_frames": self.train_frames, "colour_cameras": list(self.capture.split.train_views)}

    def checkpoint(self, step: int) -> Path:
        """Save a checkpoint (rank 0 writes) -> its path."""
        from avatarctl.fit.checkpoint import save_checkpoint

        data = self.payload(step)
        return save_checkpoint(self.project, data, keep=self.cfg.keep_checkpoints) if self.main \
            else self.project.paths.checkpoint(step)


def _open_run(project: Project, cfg: FitConfig | None, resume: bool, fresh: bool, main: bool
              ) -> tuple[Any, list[int], FitConfig, "dict[str, Any] | None"]:
    """Check the project's split, read the checkpoint being resumed (its config holds; only `iters` may change) or
    clear the fit being replaced. -> (capture, training frames, config, checkpoint or None)."""
    from avatarctl.fit.checkpoint import read_checkpoint, saved_configs
    from avatarctl.io.project_io import load_project_capture

    paths = project.paths
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
        cfg = _resume_config(cfg, saved_configs(ckpt, paths.latest_checkpoint)[0])
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
    return capture, train_frames, cfg, ckpt


# `model.hull.tracked_nodes` and the garment tracking pass need this many training views: synth small (8 views, 15 min)
# +0.15 dB held-out on both seeds with the tracked model; synth realistic (3 views, 300 s) -0.14 / -0.18 with it, and
# the tracker itself -0.02 / -0.25 / -0.19 (seeds 0 / 1 / 7) against none: its tube from MediaPipe's masks is farther
# from the cloth than the skeleton (docs/experiments/garment_tracking_ceiling_2026-11-30/, realistic_costs_2026-12-02/)
TRACKED_NODES_MIN_VIEWS = 4


def _decide_hull(cfg: FitConfig, capture, body, template, train_frames: list[int], ranks: int
                 ) -> "tuple[FitConfig, HullNodes | None, str | None]":
    """A fresh fit's hull nodes (`_place_hull_nodes`), and the model of a fit that will track a loose garment
    (`ModelConfig.for_tracked_garment` where `model.hull.tracked_nodes` asks for it: `track` on, hull nodes placed,
    `TRACKED_NODES_MIN_VIEWS` training views or more, one process; its hull nodes placed again for it; elsewhere
    `model.track_refine.enabled = "auto"` is decided off). -> (the config to train and save, the hull nodes or
    None, the survey's line or None)."""
    hull, note = None, None
    if cfg.model.hull.on and cfg.model.variant == "slrf":
        views = list(capture.split.train_views)
        hull, note = _place_hull_nodes(cfg.model, cfg.seed, capture, body, template, train_frames, views)
        garment = cfg.model.for_tracked_garment()
        if hull is not None and cfg.track and len(views) >= TRACKED_NODES_MIN_VIEWS and ranks == 1 \
                and garment is not cfg.model:
            cfg = replace(cfg, model=garment)
            hull, note = _place_hull_nodes(garment, cfg.seed, capture, body, template, train_frames, views)
            note += f" (garment tracking: {garment.gaussians.per_node} Gaussians per node)"
    if cfg.model.track_refine.enabled == AUTO:
        cfg = replace(cfg, model=cfg.model.with_(track_refine={"enabled": False}))
    return cfg, hull, note


def _build_model(cfg: FitConfig, capture, body, template, poses, train_frames: list[int], *,
                 hull: "HullNodes | None", fresh_fit: bool, dev: torch.device) -> "tuple[Any, int]":
    """The avatar, initialised from `cfg.seed` with the hull nodes `hull` of a fresh fit (`_decide_hull`); a fresh
    fit solves the pose refinement's joint centres first, a resumed one gets them and its nodes from the checkpoint.
    In training mode. -> (model, the number of hull nodes: the last nodes)."""
    from avatarctl.model.avatar import SlrfAvatar

    with torch.random.fork_rng(devices=[]):  # weights initialised from cfg.seed, global RNG left as it was
        torch.manual_seed(cfg.seed)
        model = SlrfAvatar(cfg.model, template, num_frames=len(train_frames), seed=cfg.seed,
                           hull_nodes=None if hull is None else (hull.rest, hull.vertex),
                           off_body=None if hull is None else (torch.from_numpy(hull.survey.cells), hull.survey.cell),
                           cameras=tuple(capture.split.train_views)).to(dev)
    if model.pose_refine is not None and fresh_fit:  # canonical joint centres from the training poses
        from avatarctl.body.joints import joint_centres, skin_weighted_centroids

        model.pose_refine.set_centres(joint_centres(poses.joint_transforms, template.parents,
                                                    skin_weighted_centroids(template.vertices, template.skin_weights)))
    model.train()
    return model, 0 if hull is None else int(hull.rest.shape[0])


def _set_up(project: Project, cfg: FitConfig | None, device: str, resume: bool, fresh: bool,
            env: "DistEnv | None", shards: int | None) -> "tuple[_Trainer, _Log | None]":
    """Open the run, write the config, build the data, the model, the optimiser and the log (restored from the
    checkpoint on resume)."""
    from avatarctl.body.registry import load_body_model
    from avatarctl.fit.conditioning import build_pose_table, make_conditioning, time_stamps
    from avatarctl.fit.data import FrameStore
    from avatarctl.fit.distributed import Replicas, saved_shards
    from avatarctl.fit.steps import training_steps
    from avatarctl.fit.schedule import make_optimizer, make_scheduler, param_groups
    from avatarctl.fit.validate import Validator, choose_val_pairs

    paths = project.paths
    dev = rank_device(env, resolve_device(device))
    main = env is None or env.is_main
    capture, train_frames, cfg, ckpt = _open_run(project, cfg, resume, fresh, main)
    split = capture.split
    start_step = int(ckpt["step"]) if ckpt is not None else 0
    world = env.world_size if env is not None else 1
    if shards is None:
        shards = world if ckpt is None else saved_shards(ckpt["rng"])
        shards = shards if shards % world == 0 else world
    body = load_body_model(capture.body_model, capture.body_model_path)
    template = body.template(capture.motion)
    hull, hull_note = None, None
    if ckpt is None:  # a fresh fit: its hull nodes, and the model decided with them
        cfg, hull, hull_note = _decide_hull(cfg, capture, body, template, train_frames, world)
    if main:
        write_json(paths.fit_config, cfg.to_json())

    poses = build_pose_table(body, capture.motion, train_frames)
    store = FrameStore(capture, poses, cfg.crop_pad, cfg.cache_mb * 2**20)
    # the ray-marched fields learn from scattered rays, the rasterized one (model.field = "gaussians") from whole crops
    steps = training_steps(cfg.model)
    replicas = Replicas(env, shards, steps, lambda pairs, rays, images: steps.sampler(
        store, cfg, train_frames, list(split.train_views), pairs, rays, images), train_frames,
        list(split.train_views), cfg.rays_per_batch, cfg.images_per_batch, cfg.seed, dev)
    pairs = choose_val_pairs(split.test_views, train_frames, cfg.val_pairs) if main else []
    validator = Validator(capture, body, pairs, train_frames, cfg.background, cfg.val_scale) if pairs else None

    model, hull_count = _build_model(cfg, capture, body, template, poses, train_frames, hull=hull,
                                     fresh_fit=ckpt is None, dev=dev)
    optimizer = make_optimizer(cfg, param_groups(cfg, model))
    scheduler = make_scheduler(cfg, optimizer)
    same_stream = True
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
    all_frames = make_conditioning(poses.joint_transforms, poses.pose_features,
                                   *time_stamps(train_frames, train_frames, True), device=dev)
    trainer = _Trainer(project=project, cfg=cfg, dev=dev, env=env, shards=shards, capture=capture, body=body,
                       template=template, poses=poses, train_frames=train_frames, store=store, replicas=replicas,
                       validator=validator, model=model, optimizer=optimizer, scheduler=scheduler,
                       background=torch.tensor(cfg.background, dtype=torch.float32, device=dev),
                       all_frames=all_frames, start_step=start_step, resumed=ckpt is not None, hull_note=hull_note)
    if cfg.track and ckpt is None:
        trainer.track_note, trainer.track_seconds = _track_garment(trainer, template, hull_count)
        if log is not None:
            log.append({"step": 0, "note": trainer.track_note})
    return trainer, log


def _track_garment(t: "_Trainer", template, hull_count: int) -> tuple[str, float]:
    """The garment tracking pass (fit/garment_track.py) of a fresh fit: the reference surface at the middle training
    frame, tracked through the training frames (and rescued where lost, with `track_rescue`); the last `hull_count`
    nodes (the hull nodes) that own a patch of it are placed by its motion on training frames
    (`SlrfAvatar.set_tracks`). Writes fit/track/summary.json and tracks.npz (the surface per frame). -> (the line for
    the log, seconds)."""
    import numpy as np

    from avatarctl.body.lbs import transform_points
    from avatarctl.fit import garment_track as gt

    t0 = time.perf_counter()
    views = list(t.capture.split.train_views)
    if not hull_count:
        return "garment tracking: skipped (no hull nodes: no loose garment found)", 0.0
    if len(views) < 2:
        return "garment tracking: skipped (one training view: the cloth cannot be placed in depth)", 0.0
    if len(views) < TRACKED_NODES_MIN_VIEWS:
        return (f"garment tracking: skipped ({len(views)} training views: from so few masks the tracked surface places "
                f"the garment worse than the skeleton; {TRACKED_NODES_MIN_VIEWS} or more)"), 0.0
    if t.replicas.distributed:
        return "garment tracking: skipped (one process only; run without --nproc)", 0.0
    inp = gt.capture_input(t.capture, t.body, template, t.train_frames, views)
    ref = len(t.train_frames) // 2
    settings = gt.TrackSettings()
    mesh = gt.refine_reference(inp, gt.reference_mesh(inp, ref, settings), ref, settings, device=t.dev)
    if len(mesh.vertices) < 20:
        return "garment tracking: skipped (the masks show no garment off the body at the reference frame)", 0.0
    tracks = followed = gt.track(inp, mesh, ref, settings, device=t.dev)
    if t.cfg.track_rescue:
        tracks = gt.rescue(inp, followed, ref, settings, device=t.dev)
    rescued = int(tracks.tracked.sum() - followed.tracked.sum())
    model, N = t.model, t.cfg.model.num_nodes
    nodes = torch.arange(N - hull_count, N)
    with torch.no_grad():  # the hull nodes placed by the skeleton on every training frame (Eq. 1, 3, Delta n = 0)
        T = model.node_state(t.all_frames, mode="zero").transforms[:, nodes].double().cpu()  # [F, M, 4, 4]
    A = T[..., :3, :3].numpy()  # [F, M, 3, 3]
    c = transform_points(T, model.node_rest[nodes].double().cpu()).numpy()  # [F, M, 3] Eq. 2

    def placed(tr: "gt.GarmentTracks") -> tuple["gt.NodeMotions", np.ndarray, np.ndarray]:
        motion = gt.node_motions(tr, ref, nodes.numpy(), c[ref])
        keep = np.searchsorted(nodes.numpy(), motion.nodes)
        R, shift = motion.rotation, motion.translation  # [F, M', 3, 3], [F, M', 3]
        rotation = R @ A[ref, keep][None]
        center = np.einsum("fmij,mj->fmi", R, c[ref, keep]) + shift
        return (motion, *gt.placement(rotation, center, A[:, keep], c[:, keep], tr.tracked, ref))

    motion, rotation, center = placed(tracks)
    # Delta n is pulled to the placement without the rescue (its offsets on the rescued frames cost novel poses)
    pull = placed(followed)[2] - center if tracks is not followed else np.zeros_like(center)
    if len(motion.nodes):
        model.set_tracks(torch.as_tensor(motion.nodes), torch.as_tensor(rotation), torch.as_tensor(center),
                         torch.as_tensor(pull))
    seconds = time.perf_counter() - t0
    folder = t.project.paths.fit / "track"
    folder.mkdir(parents=True, exist_ok=True)
    with atomic_path(folder / "tracks.npz") as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, frames=np.asarray(tracks.frames), vertices=tracks.vertices.astype(np.float32),
                                faces=mesh.faces, seen=tracks.seen, loss=tracks.loss, tracked=tracks.tracked,
                                reference=ref, nodes=motion.nodes, segments=mesh.segments)
    summary = {"reference_frame": int(t.train_frames[ref]), "surface_vertices": int(len(mesh.vertices)),
               "frames": len(tracks.frames), "tracked_nodes": int(len(motion.nodes)), "hull_nodes": hull_count,
               "patch_vertices_median": float(np.median(motion.vertices)) if len(motion.nodes) else 0.0,
               "seen_by_two_views": float((tracks.seen >= 2).mean()), "frames_tracked": int(tracks.tracked.sum()),
               "frames_rescued": rescued,
               "loss": [round(float(x), 3) for x in tracks.loss], "seconds": round(seconds, 1),
               "settings": {k: (list(v) if isinstance(v, tuple) else v) for k, v in vars(settings).items()}}
    write_json(folder / "summary.json", summary)
    note = (f"garment tracking: {len(mesh.vertices)} surface vertices through {int(tracks.tracked.sum())} of "
            f"{len(tracks.frames)} frames{f' ({rescued} rescued)' if t.cfg.track_rescue else ''}, "
            f"{len(motion.nodes)} of {hull_count} hull nodes placed by it ({seconds:.0f} s)")
    return note, seconds


def _pose_held_out(t: _Trainer, step: int, progress: Callable[[Any], None] | None) -> dict[str, Any] | None:
    """The held-out frames posed against the training views' masks (fit/held_out_poses.py), written as
    fit/held_out_poses.npz -> its summary and "path" ({"skipped": why} where it does not apply, None when off);
    `progress` gets a `ProgressReport` per frame (part "held-out poses"). With a time budget the pass takes at most
    as long again (the frames it has no time for keep ingest's poses)."""
    from avatarctl.fit.held_out_poses import FILE_NAME, held_out_frames, pose_held_out_frames

    cfg = t.cfg
    if not cfg.held_out_poses or t.model.pose_refine is None:  # off, or the body fits are taken as they are
        return None
    if not t.model.field_kind.splats:
        return {"skipped": f"model.field {cfg.model.field!r}: posing renders whole crops (Gaussian fields only)"}
    frames = held_out_frames(t.capture, t.train_frames)
    if not frames:
        return {"skipped": "the capture has no held-out frames"}

    poses = pose_held_out_frames(t.model, t.template, t.body, t.capture, t.train_frames, cfg.background, step,
                                 cfg.held_out_poses, progress, limit_s=cfg.time_budget_s or None)
    path = t.project.paths.fit / FILE_NAME
    poses.save(path)
    return {**poses.summary(), "path": str(path)}


# ---- one step ----------------------------------------------------------------------------------------------------
@dataclass
class _Step:
    """What one optimisation step leaves for the bookkeeping."""

    terms: Any  # LossTerms
    out: Any  # RenderOutputs (its stats go to the log)
    rays: int  # rays (pixels) trained on
    agreed: "StepSync"  # what the ranks agreed on after it


def _train_step(t: _Trainer, step: int, elapsed_s: Callable[[], float], stop: StopFlag,
                next_snapshot_s: float | None) -> _Step:
    """One optimisation step (paper Sec. 4): forward and loss on this rank's share of the batch (samples jittered),
    backward, the ranks' synchronisation, Adam (no gradient clipping, as the paper) and the lr schedule; then the
    Gaussians' density control when due. `step`: the steps done before this one."""
    cfg, model = t.cfg, t.model
    occ_start = t.replicas.begin_step(model)
    use_amp = cfg.amp and t.dev.type == "cuda"
    with torch.autocast(device_type="cuda", dtype=torch.bfloat16) if use_amp else contextlib.nullcontext():
        terms, out, step_rays = t.replicas.forward(model, t.background, jitter=True)
    t.optimizer.zero_grad(set_to_none=True)
    terms.total.backward()
    elapsed = elapsed_s()
    agreed = t.replicas.sync(model, terms, occ_start, stop=stop.is_set(),
                             budget=t.main and bool(cfg.time_budget_s) and elapsed >= cfg.time_budget_s,
                             snapshot=t.main and next_snapshot_s is not None and elapsed >= next_snapshot_s)
    t.optimizer.step()
    t.scheduler.step()
    model.field_kind.density_control(model, t.optimizer, step + 1, cfg.seed)  # e.g. the Gaussians' relocation
    return _Step(terms, out, step_rays, agreed)


# ---- bookkeeping -------------------------------------------------------------------------------------------------
class _Books:
    """After each step: the log record (losses, speed, cache, model stats), validation, checkpoints, time snapshots
    and the progress report; it keeps what the result needs (latest losses, validation, checkpoint)."""

    def __init__(self, t: _Trainer, log: "_Log | None", progress: Callable[[StepReport], None] | None):
        self.t, self.log, self.progress = t, log, progress
        self.t_run = time.perf_counter() - t.track_seconds  # the tracking pass counts towards the budget
        self.losses: dict[str, float] = {}
        self.val: ValidationResult | None = None
        self.last_ckpt: Path | None = t.project.paths.latest_checkpoint if t.resumed else None
        self.saved_step = t.start_step if t.resumed else -1
        self.window_t, self.window_rays, self.rays_per_s = time.perf_counter(), 0, 0.0
        self.snapshots = list(t.cfg.snapshot_at_s)

    def elapsed(self) -> float:
        """Seconds of training in this run."""
        return time.perf_counter() - self.t_run

    @property
    def next_snapshot_s(self) -> float | None:
        return self.snapshots[0] if self.snapshots else None

    def after_step(self, step: int, s: _Step) -> None:
        """`step`: the steps done, this one included."""
        t, cfg = self.t, self.t.cfg
        self.window_rays += s.rays
        record: dict[str, Any] = {}
        if step % cfg.log_every == 0 or step == cfg.iters:
            self.losses = s.agreed.losses or s.terms.as_floats()
            if not all(math.isfinite(v) for v in self.losses.values()):
                raise AvatarError(f"training diverged: non-finite loss at step {step} ({self.losses})",
                                  where=str(t.project.paths.fit),
                                  fix="resume from the last checkpoint with a lower lr (--fresh --set lr=...)")
            now = time.perf_counter()
            self.rays_per_s = self.window_rays / max(now - self.window_t, 1e-9)
            self.window_t, self.window_rays = now, 0
            record = {"lr": t.optimizer.param_groups[0]["lr"], "loss": self.losses,
                      "rays_per_s": round(self.rays_per_s, 1),
                      "cache": {"images": len(t.store), "mb": round(t.store.cached_bytes / 2**20, 1),
                                "hits": t.store.hits, "misses": t.store.misses},
                      "stats": {k: float(v) for k, v in s.out.stats.items()}}
        if t.validator is not None and cfg.val_every and step % cfg.val_every == 0:
            self.val = t.validator.score(t.model)
            record["val"] = _val_record(self.val)
        if record and self.log is not None:
            self.log.append({"step": step, "time": round(self.elapsed(), 3), **record})
        if step % cfg.checkpoint_every == 0:
            self.last_ckpt, self.saved_step = t.checkpoint(step), step
        self._snapshots(step, s.agreed.snapshot)
        if self.progress is not None:
            self.progress(StepReport(step=step, iters=cfg.iters, start_step=t.start_step, losses=self.losses,
                                     lr=t.optimizer.param_groups[0]["lr"], rays_per_s=self.rays_per_s,
                                     val_psnr=None if self.val is None else self.val.psnr))

    def _snapshots(self, step: int, agreed: bool) -> None:
        """checkpoints/snapshot_<s>s.pt for each `snapshot_at_s` time passed (several ranks: when they agreed)."""
        from avatarctl.fit.checkpoint import save_snapshot

        t = self.t
        while self.snapshots and (agreed if t.replicas.distributed else self.elapsed() >= self.snapshots[0]):
            data = t.payload(step)
            if t.main:
                save_snapshot(t.project, data, self.snapshots[0])
            self.snapshots.pop(0)
            agreed = False


# ---- the loop and its stop ---------------------------------------------------------------------------------------
def fit(project: Project, cfg: FitConfig | None = None, *, device: str = "auto", resume: bool = False,
        fresh: bool = False, progress: Callable[[Any], None] | None = None, stop: StopFlag | None = None,
        handle_sigint: bool = True, env: "DistEnv | None" = None, shards: int | None = None) -> FitResult:
    """Train (or resume training) the project's avatar; see the module docstring. `cfg` may be None on resume.
    `progress` gets a `StepReport` per step, then a `ProgressReport` per held-out frame posed (`_pose_held_out`).
    `env`: this process's rank in a started group (None: one process); `shards`: ray shards (fit/distributed.py;
    None = the world size for a fresh fit, the checkpoint's on resume when the world size divides them). The stop
    rule: before a step, a stop asked for (one process: the local flag; ranks: the flag they agreed on after the last
    step) or the time budget spent; after a step, the budget the ranks agreed on."""
    t_setup = time.perf_counter()
    started = now_iso()
    t, log = _set_up(project, cfg, device, resume, fresh, env, shards)
    if t.main:  # the held-out frames' poses belong to the checkpoint this run replaces (fit/held_out_poses.py)
        from avatarctl.fit.held_out_poses import remove_held_out_poses

        remove_held_out_poses(project.paths.fit)
    stop = stop or StopFlag()
    setup_seconds = time.perf_counter() - t_setup
    books = _Books(t, log, progress)
    step, last, budget_hit = t.start_step, None, False
    with _sigint_sets(stop) if handle_sigint else contextlib.nullcontext():
        agreed_stop = False  # several ranks stop on the flags they agreed on, never on a local one
        while step < t.cfg.iters and not (agreed_stop if t.replicas.distributed else stop.is_set()):
            if not t.replicas.distributed and t.cfg.time_budget_s and books.elapsed() >= t.cfg.time_budget_s:
                budget_hit = True
                break
            last = _train_step(t, step, books.elapsed, stop, books.next_snapshot_s)
            step += 1
            books.after_step(step, last)
            agreed_stop = agreed_stop or last.agreed.stop
            if last.agreed.budget:
                budget_hit = True
                break
    return _finish(t, books, step, last, budget_hit, resume, started, setup_seconds, progress)


def _finish(t: _Trainer, books: _Books, step: int, last: _Step | None, budget_hit: bool, resume: bool,
            started: str, setup_seconds: float, progress: Callable[[Any], None] | None = None) -> FitResult:
    """After the last step: a checkpoint of it, the final validation (not when interrupted), the refined fits, the
    held-out frames' poses (not when interrupted), the project record."""
    cfg, paths = t.cfg, t.project.paths
    seconds = books.elapsed()
    if last is not None and step % cfg.log_every:  # stopped between log steps: report the last step's losses
        books.losses = last.agreed.losses or last.terms.as_floats()
    interrupted = step < cfg.iters and not budget_hit
    stop_reason = "interrupted" if interrupted else ("time_budget" if budget_hit else "done")
    if books.saved_step != step:
        books.last_ckpt = t.checkpoint(step)
    val = books.val
    if t.validator is not None and not interrupted and (val is None or not cfg.val_every or step % cfg.val_every):
        val = t.validator.score(t.model)
        assert books.log is not None
        books.log.append({"step": step, "time": round(books.elapsed(), 3), "val": _val_record(val)})
    assert books.last_ckpt is not None
    refinement = None
    if t.main and t.model.pose_refine is not None:  # the refined fits as a motion file (fit/refined.py)
        from avatarctl.fit.refined import write_refined_fits

        refinement = write_refined_fits(paths.fit, t.body, t.capture.motion, t.poses, t.model.pose_refine)
    held_out = _pose_held_out(t, step, progress) if t.main and not interrupted else None
    losses, rays_per_s = books.losses, books.rays_per_s
    summary = {"step": step, "iters": cfg.iters, "start_step": t.start_step, "interrupted": interrupted,
               "stop_reason": stop_reason,
               "seconds": round(seconds, 2), "setup_seconds": round(setup_seconds, 2), "losses": losses,
               "rays_per_s": round(rays_per_s, 1), "device": str(t.dev),
               "val_psnr_bbox": None if val is None else val.psnr,
               "val_pairs": None if val is None else val.to_json()["pairs"], "ranks": t.world, "ray_shards": t.shards,
               "pose_refinement": None if refinement is None else refinement.to_json(), "hull_nodes": t.hull_note,
               "garment_tracking": t.track_note, "held_out_poses": held_out,
               **config_summary(cfg)}
    if t.main:
        t.project.record("fit", {"fit": cfg.to_json(), "device": str(t.dev), "resume": resume, "ranks": t.world,
                                 "ray_shards": t.shards},
                         [paths.fit_config, paths.fit_log, paths.latest_checkpoint]
                         + ([refinement.path] if refinement is not None and refinement.path else [])
                         + ([Path(held_out["path"])] if held_out and "path" in held_out else []),
                         started,
                         summary)
    return FitResult(step=step, iters=cfg.iters, interrupted=interrupted, stop_reason=stop_reason,
                     checkpoint=books.last_ckpt, seconds=seconds,
                     setup_seconds=setup_seconds, losses=losses, val=val, rays_per_s=rays_per_s, device=str(t.dev),
                     config=cfg, refinement=refinement, hull_nodes=t.hull_note,
                     garment_tracking=t.track_note, held_out_poses=held_out)
