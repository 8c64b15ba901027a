"""`avatarctl demo OUT`: the whole data flow on a synthetic capture, end to end.

    synth (OUT/capture) -> ingest (OUT/project) -> fit -> render orbit + novel poses -> eval novel view / novel pose

Each stage is the same `run` its command calls (`avatarctl.stages.synth`, `.ingest`, `.fit`, `.render`,
`.evaluate`); the demo only chooses sizes, and relabels their `ProgressReport` ("render orbit", "eval novel_view", ...).
Presets (`DEMO_PRESETS`):

- `ci` (alias `micro`): synth "micro" (4 views, 6 + 4 frames, 64 px), fit "micro" preset for 20 steps. About a
  minute on 2 cores; checks the plumbing, the avatar is not recognisable.
- `tiny`: synth "tiny" (6 views, 24 + 12 frames, 96 px), fit "cpu" preset (the Gaussian local fields) for 2000
  steps or 90 s of training, whichever comes first, an orbit video of 48 views at 256 px: 1:55-1:59 in all on an
  idle 2-core machine with the 16 x 128 px orbit of before (2:12 with this one on a slower day, the orbit's render
  3.7 s), novel-view bbox PSNR 22.56-22.89 dB (seeds 0 / 1, 2026-11-28, the Gaussians shaded; docs/render_eval.md;
  until 2026-11-27 the MLP fields for 2000 steps / 330 s: 4.3-4.7 min, 22.28-22.51 dB).
- `small`: synth "small" (12 views, 80 + 40 frames, 256 px), fit "cpu" preset for 3000 steps: 13.2 min in all on an
  idle 2-core machine (the fit 10.6 min), novel-view bbox PSNR 22.78 dB (docs/render_eval.md; with the MLP fields,
  the cpu preset until 2026-11-27, 71.5 min on one thread of a busy machine, two thirds of it rendering and eval).

OUT must not exist or be empty. Stage outputs are written atomically by each stage.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

from avatarctl.errors import InputError
from avatarctl.progress import ProgressFn, relabel

if TYPE_CHECKING:
    from avatarctl.evaluate.report import EvalMetrics


@dataclass(frozen=True)
class DemoPreset:
    """Sizes of every stage of one demo preset."""

    synth: str  # SynthConfig preset
    fit_preset: str  # FitConfig preset
    iters: int  # fit steps
    fit_settings: dict[str, Any]  # FitConfig values over the fit preset's
    orbit_views: int  # cameras of the orbit video (one turn)
    orbit_resolution: int  # orbit image side, pixels
    eval_every: int  # keep every N-th frame in eval


DEMO_PRESETS: dict[str, DemoPreset] = {
    "ci": DemoPreset(synth="micro", fit_preset="micro", iters=20, fit_settings={},
                     orbit_views=4, orbit_resolution=48, eval_every=2),
    "tiny": DemoPreset(synth="tiny", fit_preset="cpu", iters=2000,
                       # no garment tracking: its pass takes 15 of the 90 s and the fit loses 0.27 dB novel view
                       fit_settings={"val_every": 500, "checkpoint_every": 500, "time_budget_s": 90.0,
                                     "track": False},
                       orbit_views=48, orbit_resolution=256, eval_every=2),
    "small": DemoPreset(synth="small", fit_preset="cpu", iters=3000,
                        fit_settings={"val_every": 500, "checkpoint_every": 500},
                        orbit_views=36, orbit_resolution=256, eval_every=4),
}
ALIASES = {"micro": "ci"}


@dataclass(frozen=True)
class DemoConfig:
    out: Path  # demo folder: OUT/capture, OUT/project
    preset: str = "tiny"  # ci | micro | tiny | small
    seed: int = 0
    iters: int | None = None  # override the preset's fit steps
    device: str = "auto"

    def __post_init__(self) -> None:
        object.__setattr__(self, "out", Path(self.out))
        name = ALIASES.get(self.preset, self.preset)
        if name not in DEMO_PRESETS:
            raise InputError(f"unknown demo preset {self.preset!r}", where="--preset",
                             fix=f"use one of: {', '.join(list(DEMO_PRESETS) + list(ALIASES))}")
        object.__setattr__(self, "preset", name)
        if self.iters is not None and self.iters < 1:
            raise InputError(f"--iters must be >= 1, got {self.iters}", where="--iters", fix="e.g. --iters 400")

    @property
    def sizes(self) -> DemoPreset:
        p = DEMO_PRESETS[self.preset]
        return p if self.iters is None else replace(p, iters=self.iters)


@dataclass(frozen=True)
class StageDone:
    """Reported after each stage."""

    stage: str  # synth | ingest | fit | render | eval
    seconds: float
    summary: dict[str, Any]  # short, printable


@dataclass
class DemoResult:
    out: Path
    capture: Path
    project: Path
    videos: dict[str, Path] = field(default_factory=dict)  # render name -> video.mp4
    metrics: "dict[str, EvalMetrics]" = field(default_factory=dict)  # split -> metrics.json contents
    metrics_paths: dict[str, Path] = field(default_factory=dict)
    stages: list[StageDone] = field(default_factory=list)
    seconds: float = 0.0


StageFn = Callable[[StageDone], None]


def run(out: str | Path, cfg: DemoConfig, progress: ProgressFn | None = None,
        on_stage: StageFn | None = None) -> DemoResult:
    """Run every stage into `out` (= `cfg.out`; see the module docstring); `on_stage` gets each stage's summary as
    soon as it is done."""
    from avatarctl.ingest.config import IngestConfig
    from avatarctl.stages import evaluate, fit, ingest, render, synth
    from avatarctl.stages.evaluate import EvalConfig
    from avatarctl.stages.fit import FitRequest
    from avatarctl.stages.render import RenderConfig
    from avatarctl.synth import SynthConfig

    cfg = replace(cfg, out=Path(out))
    out = cfg.out
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise InputError("demo output folder exists and is not empty", where=str(out),
                         fix="choose a new OUT folder (the demo writes OUT/capture and OUT/project)")
    sizes = cfg.sizes
    capture, project_dir = out / "capture", out / "project"
    result = DemoResult(out=out, capture=capture, project=project_dir)
    t_all = time.perf_counter()

    def done(stage: str, t0: float, summary: dict[str, Any]) -> None:
        s = StageDone(stage=stage, seconds=time.perf_counter() - t0, summary=summary)
        result.stages.append(s)
        if on_stage is not None:
            on_stage(s)

    # 1. synth
    t0 = time.perf_counter()
    out.mkdir(parents=True, exist_ok=True)
    syn = synth.run(capture, SynthConfig.preset(sizes.synth, cfg.seed), progress=progress)
    done("synth", t0, {"capture": str(capture), "views": len(syn.cameras), "train frames": len(syn.train_frames),
                       "test frames": len(syn.test_frames), "size": f"{syn.cameras[0].width}x{syn.cameras[0].height}"})

    # 2. ingest
    t0 = time.perf_counter()
    ing = ingest.run(project_dir, IngestConfig(capture=capture, project=project_dir), progress=progress)
    done("ingest", t0, {"project": str(project_dir), "format": ing.format, "cameras": len(ing.cameras),
                        "frames": len(ing.frames), "masks": ing.masks_source,
                        "body inside masks": f"{ing.vertices_inside_masks:.3f}"})

    # 3. fit
    t0 = time.perf_counter()
    fr = fit.run(project_dir, FitRequest(preset=sizes.fit_preset, iters=sizes.iters, seed=cfg.seed,
                                         settings=sizes.fit_settings, device=cfg.device),
                 progress=progress, handle_sigint=False)
    fit_cfg = fr.config
    val = None if fr.val is None else fr.val.psnr
    stopped = {"time_budget": f"the time budget ({fit_cfg.time_budget_s:g} s)", "done": "the step count",
               "interrupted": "interrupted"}[fr.stop_reason]
    done("fit", t0, {"steps": fr.step, "stopped by": stopped, "preset": fit_cfg.preset,
                     "images/step": fit_cfg.images_per_batch,
                     "rays (pixels)/s": round(fr.rays_per_s), "loss": round(fr.losses.get("total", float("nan")), 5),
                     "held-out PSNR (bbox)": None if val is None else round(val, 2)})

    # 4. render: an orbit over the training frames, and the novel poses from a held-out view
    for name, rcfg in (
        ("orbit", RenderConfig(name="orbit", frames="train", orbit=sizes.orbit_views,
                               resolution=sizes.orbit_resolution, device=cfg.device)),
        ("novel_pose", RenderConfig(name="novel_pose", frames="test", device=cfg.device)),
    ):
        t0 = time.perf_counter()
        rr = render.run(project_dir, rcfg, progress=relabel(progress, f"render {name}"))
        result.videos[name] = rr.video
        done(f"render {name}", t0, {"video": str(rr.video), "images": len(rr.images),
                                    "size": f"{rr.width}x{rr.height}",
                                    "s/image": round(rr.seconds_per_image, 3),
                                    "latent": ", ".join(f"{k} {v}" for k, v in rr.latent_counts.items())})

    # 5. eval
    for split in ("novel_view", "novel_pose"):
        t0 = time.perf_counter()
        er = evaluate.run(project_dir, EvalConfig(split=split, protocol="bbox", every=sizes.eval_every,
                                                  device=cfg.device), progress=relabel(progress, f"eval {split}"))
        result.metrics[split] = er.metrics
        result.metrics_paths[split] = er.out_dir / "metrics.json"
        done(f"eval {split}", t0, {"PSNR (bbox)": round(er.psnr, 2), "SSIM": round(er.ssim, 4),
                                   "images": er.metrics.images, "latent": er.metrics.latent,
                                   "metrics": str(er.out_dir / "metrics.json")})
    result.seconds = time.perf_counter() - t_all
    return result
