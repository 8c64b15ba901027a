"""Field evaluations per ray at equal quality: one trained avatar rendered with and without empty-space skipping.

For a checkpoint trained with `model.occupancy=true`, renders held-out views of training frames (bbox protocol, the
eval's pixels) two ways on the same weights: every sample evaluated (occupancy off: the paper's 64 uniform
samples) and occupancy skipping (early stop from the cached transmittance was tried and removed, docs/fit.md). Reports,
per way: evaluated samples and node-field evaluations ((point, node) pairs) per rendered ray, seconds per image,
PSNR against the ground truth, and PSNR of the render against the all-samples render (how much skipping changes).

    python -m benchmarks.sampling_efficiency PROJECT [--checkpoint FILE] [--images 4] [--out FILE.json]
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch


@dataclass(frozen=True)
class WayStats:
    """One way of rendering, averaged over the images."""
    field_samples_per_ray: float  # samples the field evaluated
    node_field_evals_per_ray: float  # (point, node) pairs
    seconds_per_image: float
    psnr_bbox_vs_gt: float  # dB, bbox pixels
    psnr_vs_all_samples: float | None  # dB against the all-samples render (inf: identical); None for that render


@dataclass(frozen=True)
class SamplingEfficiency:
    images: int
    ways: dict[str, WayStats]  # "all samples", "occupancy"


def main(argv: list[str] | None = None) -> SamplingEfficiency:
    from avatarctl.evaluate.metrics import psnr
    from avatarctl.evaluate.protocols import bbox_region, ground_truth
    from avatarctl.fit.checkpoint import load_avatar
    from avatarctl.project import Project
    from avatarctl.render.engine import render_view

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("project", type=Path)
    ap.add_argument("--checkpoint", type=Path, default=None)
    ap.add_argument("--images", type=int, default=4)
    ap.add_argument("--out", type=Path, default=None, help="write the results as JSON here")
    args = ap.parse_args(argv)

    av = load_avatar(Project.open(args.project), device="cpu", checkpoint=args.checkpoint)
    if not av.model_config.occupancy.enabled:
        raise SystemExit("this avatar was trained without model.occupancy=true: it has no occupancy grids")
    cap, model = av.capture, av.model
    views = list(cap.split.test_views)
    frames = av.train_frames[:: max(1, len(av.train_frames) // args.images)][: args.images]
    bg = np.asarray(av.fit_config.background, dtype=np.float32)
    ways = {"all samples": model.cfg.with_(occupancy={"enabled": False}), "occupancy": model.cfg}
    stats = {name: {"samples": 0.0, "pairs": 0.0, "rays": 0, "seconds": 0.0, "psnr_gt": [], "psnr_vs_all": []}
             for name in ways}
    for k, frame in enumerate(frames):
        cam = cap.cameras[views[k % len(views)]].pinhole()
        one = cap.motion.for_frames([frame])
        cond = av.conditioning(one, frames_are_training=True)
        verts = av.body.pose(one).vertices[0].detach().cpu().numpy()
        region = bbox_region(cam, verts, pad=0.05)
        gt = ground_truth(cap.image(cam.name, frame), cap.mask(cam.name, frame), bg)
        ref = None
        for name, cfg in ways.items():
            model.cfg = cfg
            counts = {"samples": 0.0, "pairs": 0.0}
            orig = model.query

            def counting(*a, _orig=orig, _c=counts, **kw):
                rgb, sigma, st = _orig(*a, **kw)
                _c["samples"] += st.get("samples", 0.0)
                _c["pairs"] += st.get("pairs", 0.0)
                return rgb, sigma, st

            model.query = counting
            with torch.no_grad():
                st = model.node_state(cond, mode="mean")
                t0 = time.perf_counter()
                v = render_view(model, st, 0, cam, av.fit_config.background, pixel_mask=region.mask)
                dt = time.perf_counter() - t0
            del model.query
            m = region.mask
            s = stats[name]
            s["samples"] += counts["samples"]
            s["pairs"] += counts["pairs"]
            s["rays"] += v.rays
            s["seconds"] += dt
            s["psnr_gt"].append(psnr(v.rgb, gt, m))
            if ref is None:
                ref = v.rgb
            else:
                s["psnr_vs_all"].append(psnr(v.rgb, ref, m))
    model.cfg = ways["all samples"]
    out = {}
    for name, s in stats.items():
        rays = max(s["rays"], 1)
        o = out[name] = WayStats(
            field_samples_per_ray=s["samples"] / rays, node_field_evals_per_ray=s["pairs"] / rays,
            seconds_per_image=s["seconds"] / len(frames), psnr_bbox_vs_gt=float(np.mean(s["psnr_gt"])),
            psnr_vs_all_samples=float(np.mean(s["psnr_vs_all"])) if s["psnr_vs_all"] else None)
        vs = o.psnr_vs_all_samples
        print(f"{name:>24}: {o.field_samples_per_ray:6.1f} samples/ray  {o.node_field_evals_per_ray:7.1f} "
              f"node-field evals/ray  {o.seconds_per_image:6.2f} s/image  PSNR {o.psnr_bbox_vs_gt:.2f} dB"
              + ("" if vs is None else f"  (vs all-samples render {vs:.1f} dB)"))
    res = SamplingEfficiency(images=len(frames), ways=out)
    if args.out:
        args.out.write_text(json.dumps({"images": len(frames), "checkpoint": str(args.checkpoint or "latest"),
                                        "protocol": "bbox pixels of held-out views of training frames, mean latent",
                                        "ways": {k: asdict(v) for k, v in out.items()}}, indent=1))
    return res


if __name__ == "__main__":
    main()
