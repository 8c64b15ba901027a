"""Profile training steps of the fit loop (torch profiler table, ms per step) on an ingested project.

    OMP_NUM_THREADS=1 python -m benchmarks.profile_step PROJECT [key=value ...] [--preset cpu-mlp] [--warmup 30]
        [--steps 10] [--rows 25]

`key=value` are fit `--set` overrides. Builds the same pieces as `avatarctl fit` (the preset's config with
`model.pose_refine.enabled = auto` decided from the capture as the fit decides it, pose table, frame store, the ray
or image sampler in `Replicas`, model, Adam with its param groups), runs `--warmup` steps, then profiles `--steps`.
Works for every field (`model.field=gaussians` trains on image crops). Hull nodes are not placed (the survey is
the fit's set-up, not its step): the nodes all start on the surface, which does not change a step's cost.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass


@dataclass(frozen=True)
class StepProfile:
    ms_per_step: float  # wall time of one profiled step (the profiler's overhead included)
    stats: dict[str, float]  # the step's own counters (images, Gaussians, pixels or rays)
    table: str  # torch profiler: ops by self CPU time


def profile_steps(project_dir: str, overrides: list[str], preset: str = "cpu-mlp", warmup: int = 30, steps: int = 10,
                  rows: int = 25) -> StepProfile:
    import torch
    from torch.profiler import ProfilerActivity, profile

    from avatarctl.body.registry import load_body_model
    from avatarctl.fit.conditioning import build_pose_table
    from avatarctl.fit.config import resolve_fit_config
    from avatarctl.fit.data import FrameStore
    from avatarctl.fit.distributed import Replicas
    from avatarctl.fit.steps import training_steps
    from avatarctl.fit.loop import decide_auto
    from avatarctl.fit.schedule import make_optimizer, param_groups
    from avatarctl.io.project_io import load_project_capture
    from avatarctl.model.avatar import SlrfAvatar
    from avatarctl.project import Project

    project = Project.open(project_dir)
    cfg = decide_auto(resolve_fit_config(preset, overrides=overrides), project)
    cap = load_project_capture(project)
    frames = sorted(int(f) for f in cap.split.train_frames)
    body = load_body_model(cap.body_model, cap.body_model_path)
    poses = build_pose_table(body, cap.motion, frames)
    store = FrameStore(cap, poses, cfg.crop_pad, 2**31)
    scheme = training_steps(cfg.model)
    views = list(cap.split.train_views)
    replicas = Replicas(None, 1, scheme, lambda pairs, rays, images: scheme.sampler(
        store, cfg, frames, views, pairs, rays, images), frames, views, cfg.rays_per_batch, cfg.images_per_batch, 0,
        torch.device("cpu"))
    torch.manual_seed(0)
    model = SlrfAvatar(cfg.model, body.template(cap.motion), num_frames=len(frames)).train()
    opt = make_optimizer(cfg, param_groups(cfg, model))
    bg = torch.zeros(3)

    def step():
        loss, out, _ = replicas.forward(model, bg, True)
        opt.zero_grad()
        loss.total.backward()
        opt.step()
        return out

    for _ in range(warmup):
        step()
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        t0 = time.perf_counter()
        for _ in range(steps):
            out = step()
        dt = (time.perf_counter() - t0) / steps
    table = prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=rows)
    return StepProfile(ms_per_step=dt * 1e3, stats=dict(out.stats), table=table)


def main(argv: list[str] | None = None) -> StepProfile:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("project")
    ap.add_argument("overrides", nargs="*", help="fit --set overrides, key=value")
    ap.add_argument("--preset", default="cpu-mlp", help="cpu-mlp (the MLP fields; the cpu preset of the figures in "
                                                        "docs/ before 2026-11-27) or cpu (the Gaussian fields)")
    ap.add_argument("--warmup", type=int, default=30)
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--rows", type=int, default=25)
    a = ap.parse_args(argv)
    res = profile_steps(a.project, a.overrides, a.preset, a.warmup, a.steps, a.rows)
    print(f"{res.ms_per_step:.1f} ms/step (profiled)", res.stats)
    print(res.table)
    return res


if __name__ == "__main__":
    main()
