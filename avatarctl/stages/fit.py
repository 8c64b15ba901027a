"""The fit stage (`avatarctl fit PROJECT`): resolve the fit config from the options (or from the checkpoint being
resumed), then train with `avatarctl.fit.loop.fit` and report each step as a `ProgressReport` (`avatarctl.progress`).

Resolution: a fresh fit takes `resolve_fit_config(preset, ablation, iters, seed, overrides)`; a resumed fit keeps
the checkpoint's config and may only change `iters`. Defaults that depend on the capture ("auto" in the config) are
decided by the loop at fit start (`fit.loop.decide_auto`) and saved decided.

Ranks (`avatarctl.dist`): `nproc > 1` spawns that many ranks on this machine (`dist.launch`); a process started
by torchrun (WORLD_SIZE in the environment) joins its group. Either way the loop trains data-parallel over ray
shards (fit/distributed.py) and rank 0 writes; in the `nproc` case the progress and result come back to this
process.
"""

from __future__ import annotations

import signal
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from avatarctl.errors import InputError
from avatarctl.project import Project
from avatarctl.progress import ProgressReport, ProgressFn
from avatarctl.stages.common import writing

if TYPE_CHECKING:
    from avatarctl.fit.config import FitConfig
    from avatarctl.fit.loop import FitResult, StopFlag


_STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


@dataclass(frozen=True)
class FitRequest:
    """What `avatarctl fit` was asked: the options that build (or keep) the `FitConfig`, and how to run."""

    preset: str | None = None  # FitConfig preset; None = `fit.config.DEFAULT_PRESET` (fresh fits only)
    iters: int | None = None  # total steps; None = the preset's (or the checkpoint's)
    seed: int | None = None
    overrides: tuple[str, ...] = ()  # `--set key=value` (the CLI's strings)
    settings: dict[str, Any] = field(default_factory=dict)  # typed FitConfig values of a caller in this process (a
    # chain: {"time_budget_s": 330.0, "val_every": 0}), applied after `overrides`
    model_settings: dict[str, Any] = field(default_factory=dict)  # ModelConfig changes of a caller in this process,
    # fixed settings included (an experiment, a test: {"gaussians": {"relocate_every": 2}}), applied last
    ablation: str | None = None  # comma list of --ablation switches
    device: str = "auto"  # auto | cpu | cuda
    resume: bool = False  # continue fit/checkpoints/latest.pt
    fresh: bool = False  # discard an existing fit
    nproc: int = 1  # ranks to spawn on this machine (1 = this process, or the torchrun group it belongs to)
    shards: int | None = None  # ray shards (fit/distributed.py); None = the number of ranks / the checkpoint's
    wait: bool = False  # another command fitting this project: wait for it to finish instead of refusing

    def __post_init__(self) -> None:
        object.__setattr__(self, "overrides", tuple(self.overrides))
        object.__setattr__(self, "settings", dict(self.settings))
        object.__setattr__(self, "model_settings", dict(self.model_settings))
        if self.nproc < 1:
            raise InputError(f"--nproc must be >= 1, got {self.nproc}", where="--nproc", fix="e.g. --nproc 2")
        if self.shards is not None and self.shards < 1:
            raise InputError(f"--shards must be >= 1, got {self.shards}", where="--shards", fix="e.g. --shards 2")

    @property
    def command(self) -> str:
        """How the lock names this fit to a command it refuses."""
        return "fit --resume" if self.resume else "fit --fresh" if self.fresh else "fit"


def fit_config(project: Project, cfg: FitRequest) -> "FitConfig | None":
    """The config to train with; None = the checkpoint's unchanged (resume without --iters)."""
    from avatarctl.fit.config import DEFAULT_PRESET, FitConfig, resolve_fit_config

    if cfg.resume and cfg.fresh:
        raise InputError("--resume and --fresh contradict each other", fix="pass one of them")
    if not cfg.resume:
        fit_cfg = resolve_fit_config(cfg.preset or DEFAULT_PRESET, ablation=cfg.ablation, iters=cfg.iters,
                                     seed=cfg.seed, overrides=list(cfg.overrides))
        fit_cfg = replace(fit_cfg, **cfg.settings) if cfg.settings else fit_cfg
        if cfg.model_settings:
            try:
                fit_cfg = replace(fit_cfg, model=fit_cfg.model.with_(**cfg.model_settings))
            except ValueError as e:
                raise InputError(str(e), where="model_settings", fix="check the ModelConfig values") from None
        return fit_cfg
    given = [n for n, v in (("--preset", cfg.preset), ("--seed", cfg.seed), ("--ablation", cfg.ablation))
             if v is not None]
    if cfg.overrides or cfg.settings or cfg.model_settings:
        given.append("--set")
    if given:
        raise InputError(f"{', '.join(given)} cannot change a fit being resumed",
                         fix="resume with only --iters (or start over with --fresh)")
    if cfg.iters is None:
        return None
    from avatarctl.fit.checkpoint import read_checkpoint, saved_configs  # extend (or shorten) the resumed run

    path = project.paths.latest_checkpoint
    saved = saved_configs(read_checkpoint(path), path)[0]
    return replace(saved, iters=cfg.iters)


@dataclass(frozen=True)
class FitPlan:
    """A fit request checked against its project (every option error is raised before training starts)."""

    project: Project
    config: "FitConfig | None"  # None = the resumed checkpoint's, unchanged


def prepare(project_dir: str | Path, cfg: FitRequest) -> FitPlan:
    from avatarctl.dist import DistEnv

    if cfg.nproc > 1 and DistEnv.from_env() is not None:
        raise InputError("--nproc inside a torchrun launch", where="--nproc",
                         fix="let torchrun start the ranks (--nproc_per_node) and drop --nproc")
    project = Project.open(project_dir)
    plan = FitPlan(project, fit_config(project, cfg))
    if cfg.nproc > 1 and plan.config is not None and not cfg.resume:  # shard errors before the ranks start
        from avatarctl.fit.distributed import check_shards
        from avatarctl.io.project_io import load_split

        project.require("ingest")
        split = load_split(project.paths.split)
        check_shards(cfg.shards or cfg.nproc, cfg.nproc, plan.config.rays_per_batch, plan.config.images_per_batch,
                     len(split.train_frames) * len(split.train_views))
    return plan


def preset_help() -> str:
    """`--preset`'s help, from the preset table (`fit.config.PRESETS`)."""
    from avatarctl.fit.presets import preset_help as text  # plain data: no torch at start-up

    return text()


def is_main_rank() -> bool:
    """False in the ranks > 0 of a torchrun launch (they print nothing)."""
    from avatarctl.dist import DistEnv

    env = DistEnv.from_env()
    return env is None or env.is_main


def run(project_dir: str | Path, cfg: FitRequest, progress: ProgressFn | None = None, *,
        plan: FitPlan | None = None, stop: "StopFlag | None" = None, handle_sigint: bool = True) -> "FitResult":
    """Train (or resume) the project's avatar; `progress` gets every step (`detail`: the loop's `StepReport`).
    `plan`: the result of `prepare(project_dir, cfg)` when the caller already has it. Holds the lock of the
    project's `fit/` (another fit of it is refused with `BusyError`, or waited for with `cfg.wait`)."""
    from avatarctl.atomic import remove_stale_temps

    plan = plan or prepare(project_dir, cfg)
    with writing(plan.project.paths.fit, cfg.command, cfg.wait) as held:
        if held:  # what a killed fit left in fit/ (its checkpoints' temporaries: the loop)
            remove_stale_temps(plan.project.paths.fit)
        return _train(plan, cfg, progress, stop, handle_sigint)


def _train(plan: FitPlan, cfg: FitRequest, progress: ProgressFn | None, stop: "StopFlag | None",
           handle_sigint: bool) -> "FitResult":
    from avatarctl.dist import DistEnv, launch, process_group, signals_request_stop
    from avatarctl.fit.loop import StepReport, StopFlag, fit

    project, fit_cfg = plan.project, plan.config
    t0 = time.perf_counter()

    def on_step(rep: "StepReport | ProgressReport") -> None:
        if progress is None:
            return
        if isinstance(rep, ProgressReport):  # a pass after the steps (the held-out frames' poses), frames done
            progress(replace(rep, stage="fit", seconds=time.perf_counter() - t0))
            return
        progress(ProgressReport(stage="fit", done=rep.step, total=rep.iters, seconds=time.perf_counter() - t0,
                                detail=rep))

    if cfg.nproc > 1:
        return launch(_fit_rank, cfg.nproc, (str(project.root), cfg), on_progress=on_step, what="fit",
                      fix=f"the last checkpoint is intact: `avatarctl fit {project.root} --resume` "
                          f"(any --nproc dividing the ray shards)")
    env = DistEnv.from_env()
    if env is None:
        return fit(project, fit_cfg, device=cfg.device, resume=cfg.resume, fresh=cfg.fresh, progress=on_step,
                   stop=stop, handle_sigint=handle_sigint, shards=cfg.shards)
    stop = stop or StopFlag()  # a torchrun rank: Ctrl-C / SIGTERM ask for a stop the ranks agree on
    with process_group(env, _device(cfg)), signals_request_stop(stop, _STOP_SIGNALS):
        return fit(project, fit_cfg, device=cfg.device, resume=cfg.resume, fresh=cfg.fresh,
                   progress=on_step if env.is_main else None, stop=stop, handle_sigint=False, env=env,
                   shards=cfg.shards)


def _device(cfg: FitRequest):
    from avatarctl.device import resolve_device

    return resolve_device(cfg.device)


def _fit_rank(env, channel, project_dir: str, cfg: FitRequest) -> "FitResult":
    """One rank spawned by `run` (`dist.launch`): join the group, train, hand rank 0's result back."""
    from avatarctl.dist import process_group, signals_request_stop
    from avatarctl.fit.loop import fit, StopFlag

    stop = StopFlag(channel.stop)
    with process_group(env, _device(cfg)), signals_request_stop(stop):
        plan = prepare(project_dir, replace(cfg, nproc=1))
        return fit(plan.project, plan.config, device=cfg.device, resume=cfg.resume, fresh=cfg.fresh,
                   progress=channel.send_progress if env.is_main else None, stop=stop, handle_sigint=False, env=env,
                   shards=cfg.shards)
