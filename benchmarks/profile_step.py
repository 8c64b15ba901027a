"""Profile training steps of the fit loop (torch profiler table, ms per step) on an ingested project.

    OMP_NUM_THREADS=1 python -m benchmarks.profile_step PROJECT [key=value ...]   (fit `--set` overrides)

Builds the same pieces as `avatarctl fit` (pose table, frame store, the ray or image sampler in `Replicas`, model,
Adam with its param groups), runs 30 warm-up steps, then profiles 10. Works for every field (`model.field=gaussians`
trains on image crops).
"""

from __future__ import annotations

import sys
import time


def main(argv: list[str] | None = None) -> None:
    import torch
    from torch.profiler import ProfilerActivity, profile

    from avatarctl.body.registry import load_body_model
    from avatarctl.fit.conditioning import build_pose_table
    from avatarctl.fit.config import MASK_DILATE_PX, resolve_fit_config
    from avatarctl.fit.data import FrameStore, ImageSampler, RaySampler
    from avatarctl.fit.distributed import Replicas
    from avatarctl.fit.schedule import make_optimizer, param_groups
    from avatarctl.io.project_io import load_project_capture
    from avatarctl.model.avatar import SlrfAvatar
    from avatarctl.project import Project

    argv = sys.argv[1:] if argv is None else argv
    cfg = resolve_fit_config("cpu", overrides=argv[1:])
    cap = load_project_capture(Project.open(argv[0]))
    frames = sorted(int(f) for f in cap.split.train_frames)
    body = load_body_model(cap.body_model, cap.body_model_path)
    poses = build_pose_table(body, cap.motion, frames)
    store = FrameStore(cap, poses, cfg.crop_pad, 2**31, MASK_DILATE_PX)
    Sampler = RaySampler if cfg.model.ray_marched else ImageSampler
    views = list(cap.split.train_views)
    replicas = Replicas(None, 1, lambda pairs, rays, images: Sampler(
        store, frames, views, rays, images, cfg.box_fraction, cfg.background, cfg.mask_fraction, pairs),
        frames, views, cfg.rays_per_batch, cfg.images_per_batch, 0, torch.device("cpu"))
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

    for _ in range(30):
        step()
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        t0 = time.perf_counter()
        for _ in range(10):
            out = step()
        dt = (time.perf_counter() - t0) / 10
    print(f"{dt * 1e3:.1f} ms/step (profiled)", out.stats)
    print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=25))


if __name__ == "__main__":
    main()
