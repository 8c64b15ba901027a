"""Benchmark: sparse (supplement Sec. C.2, packed) vs dense node evaluation, and training throughput.

    python -m benchmarks.bench [--out bench.json] [--device cpu|cuda] [--rays-paper N] [--rays-cpu N]
        [--rays-throughput N] [--repeats 2] [--steps 3] [--presets paper,cpu-mlp] [--body anny|toy]

(run from the repository root: `benchmarks/` is not part of the installed package).

Setup (realistic batch): nodes by FPS on the anny template (`load_body_model("anny")`), B = 4 frames in anny's
reference pose (`--body toy`: the tests' sphere, unbent) with different time stamps, rays from cameras on a 3 m
circle around the body aimed at points drawn uniformly in each frame's posed bounding box (so nearly every ray
crosses the body), 64 uniform samples per ray.

For each preset of the ray-marched MLP fields ("paper", "cpu-mlp": the cpu preset until 2026-11-27) and each path
(sparse, dense) on the SAME batch, in the same process:
- time per training step = node_state (cVAE posterior) + render + Eq. 11 loss + backward (median of repeats);
- peak step memory = the peak of tensor memory allocated during one step, excluding parameters and inputs
  (CUDA: `torch.cuda.max_memory_allocated` minus the allocation before the step; CPU: the allocation timeline of
  `torch.profiler` with `profile_memory=True`, since tracemalloc cannot see torch's allocator and RSS is noisy);
- the sparse/dense agreement of the rendered colours (max abs difference).
Then training throughput (rays/s, sparse, including an Adam step) at the cpu-mlp preset.

The dense path needs ~N x P x C floats per layer, so on CPU the default ray counts are smaller than the paper's
2048 (they are printed); on CUDA the default is the paper's 2048 rays in 4 frames.
"""

from __future__ import annotations

import argparse
import math
import statistics
import time
from dataclasses import dataclass
from typing import Any

import torch

from avatarctl.geometry.rays import RayBatch
from avatarctl.lists import split_list
from avatarctl.model.avatar import FrameConditioning, SlrfAvatar
from avatarctl.fit.config import preset as fit_preset


@dataclass
class Batch:
    cond: FrameConditioning
    rays: RayBatch
    target: torch.Tensor  # [rays, 3]


def rest_setup(body_name: str = "anny", num_frames: int = 4):
    """(template, joint_transforms [B, J, 4, 4], pose_features [B, J, 3], posed vertices [B, V, 3]) of `num_frames`
    frames in the body's rest pose: anny's reference pose (A-pose), or the toy sphere unbent (`--body toy`, the
    tests: no anny cache)."""
    import numpy as np

    from avatarctl.body.motion import BodyMotion
    from avatarctl.body.registry import load_body_model

    body = load_body_model(body_name)
    frames = np.arange(num_frames)
    if body_name == "anny":
        from avatarctl.body.anny_model import identity_pose

        motion = BodyMotion(body_model="anny", frame_index=frames, pose_parameters=identity_pose(num_frames))
    elif body_name == "toy":
        zeros = np.zeros((num_frames, 3), np.float32)
        motion = BodyMotion(body_model="toy", frame_index=frames, global_orient=zeros, body_pose=zeros, transl=zeros)
    else:
        raise ValueError(f"--body {body_name!r}: use anny or toy")
    posed = body.pose(motion)
    return body.template(motion), posed.joint_transforms, posed.pose_features, posed.vertices


def make_batch(joint_transforms: torch.Tensor, pose_features: torch.Tensor, vertices: torch.Tensor, rays: int,
               seed: int = 0) -> Batch:
    """`rays` rays spread over the frames, aimed at points uniform in each frame's posed bounding box."""
    g = torch.Generator().manual_seed(seed)
    B = joint_transforms.shape[0]
    slot = torch.arange(rays) % B
    lo, hi = vertices.min(dim=1).values[slot], vertices.max(dim=1).values[slot]  # [rays, 3]
    aim = lo + (hi - lo) * torch.rand(rays, 3, generator=g)
    ang = 2 * math.pi * torch.rand(rays, generator=g)
    eye = torch.stack([3 * torch.cos(ang), 3 * torch.sin(ang), 0.6 * torch.rand(rays, generator=g) - 0.3], -1)
    dirs = torch.nn.functional.normalize(aim - eye, dim=-1)
    cond = FrameConditioning(joint_transforms, pose_features, torch.arange(B, dtype=torch.float32) / max(B - 1, 1),
                             torch.arange(B))
    return Batch(cond=cond, rays=RayBatch(eye, dirs, slot), target=torch.rand(rays, 3, generator=g))


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def train_step(model: SlrfAvatar, batch: Batch, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    state = model.node_state(batch.cond, "posterior", g)
    out = model.render(batch.rays, state, torch.ones(3), jitter=True, generator=g)
    loss = model.losses(out, batch.target, state).total
    model.zero_grad(set_to_none=True)
    loss.backward()
    return out.rgb.detach()


def time_step(model: SlrfAvatar, batch: Batch, repeats: int, device: torch.device) -> float:
    train_step(model, batch)  # warm-up
    times = []
    for k in range(repeats):
        _sync(device)
        t0 = time.perf_counter()
        train_step(model, batch, seed=k)
        _sync(device)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def peak_step_memory(model: SlrfAvatar, batch: Batch, device: torch.device) -> int:
    """Peak bytes allocated during one training step, excluding what existed before it."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)
        base = torch.cuda.memory_allocated(device)
        torch.cuda.reset_peak_memory_stats(device)
        train_step(model, batch)
        torch.cuda.synchronize(device)
        return int(torch.cuda.max_memory_allocated(device) - base)
    from torch.profiler import ProfilerActivity, profile
    from torch.profiler._memory_profiler import Action  # the allocation timeline behind export_memory_timeline

    with profile(activities=[ProfilerActivity.CPU], profile_memory=True, record_shapes=True, with_stack=True) as prof:
        train_step(model, batch)
    cur = peak = 0
    for _, action, _, size in sorted(prof._memory_profile().timeline, key=lambda e: e[0]):
        if action == Action.CREATE:
            cur += size
        elif action == Action.DESTROY:
            cur -= size
        peak = max(peak, cur)
    return int(peak)


def compare(preset: str, template, batch: Batch, device: torch.device, repeats: int) -> dict[str, Any]:
    cfg = fit_preset(preset).model.with_(pose_refine={"enabled": False})
    torch.manual_seed(0)
    sparse = SlrfAvatar(cfg.with_(sparse=True), template, num_frames=4).to(device)
    dense = SlrfAvatar(cfg.with_(sparse=False), template, num_frames=4).to(device)
    dense.load_state_dict(sparse.state_dict())
    batch = Batch(batch.cond.to(device), batch.rays.to(device), batch.target.to(device))
    res: dict[str, Any] = {"preset": preset, "rays": len(batch.rays), "frames": int(batch.cond.time.shape[0]),
                           "samples_per_ray": cfg.samples_per_ray, "nodes": cfg.num_nodes}
    rgb = {}
    for name, m in (("sparse", sparse), ("dense", dense)):
        rgb[name] = train_step(m, batch)
        with torch.no_grad():
            st = m.node_state(batch.cond, "mean")
            stats = m.render(batch.rays, st, torch.ones(3)).stats
        res[name] = {"step_s": time_step(m, batch, repeats, device), "peak_bytes": peak_step_memory(m, batch, device),
                     "pairs": stats["pairs"], "packed_slots": stats["packed_slots"],
                     "max_node_samples": stats["max_node_samples"], "valid_samples": stats["valid_samples"],
                     "samples": stats["samples"]}
    res["max_abs_rgb_diff"] = float((rgb["sparse"] - rgb["dense"]).abs().max())
    res["speedup"] = res["dense"]["step_s"] / res["sparse"]["step_s"]
    res["memory_reduction"] = 1.0 - res["sparse"]["peak_bytes"] / max(res["dense"]["peak_bytes"], 1)
    s = res["sparse"]
    res["pairs_per_valid_sample"] = s["pairs"] / max(s["valid_samples"], 1)
    res["packing_fill"] = s["pairs"] / max(s["packed_slots"], 1)
    return res


def throughput(template, batch: Batch, device: torch.device, steps: int) -> dict[str, Any]:
    cfg = fit_preset("cpu-mlp").model.with_(pose_refine={"enabled": False})
    torch.manual_seed(0)
    model = SlrfAvatar(cfg, template, num_frames=4).to(device)
    opt = torch.optim.Adam(model.parameters(), lr=5e-4)
    batch = Batch(batch.cond.to(device), batch.rays.to(device), batch.target.to(device))
    train_step(model, batch)
    _sync(device)
    t0 = time.perf_counter()
    for k in range(steps):
        train_step(model, batch, seed=k)
        opt.step()
    _sync(device)
    dt = (time.perf_counter() - t0) / steps
    return {"preset": "cpu-mlp", "rays": len(batch.rays), "step_s": dt, "rays_per_s": len(batch.rays) / dt}


def main(argv: list[str] | None = None) -> dict[str, Any]:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.bench", description=__doc__.split("\n")[0])
    ap.add_argument("--out", help="write the results as JSON here")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--rays-paper", type=int, default=None, help="rays for the paper preset (CPU 48, CUDA 2048)")
    ap.add_argument("--rays-cpu", type=int, default=None, help="rays for the cpu-mlp preset (CPU 192, CUDA 2048)")
    ap.add_argument("--rays-throughput", type=int, default=1024, help="rays per step for the throughput run")
    ap.add_argument("--repeats", type=int, default=2, help="timed steps per path (median)")
    ap.add_argument("--steps", type=int, default=3, help="steps for the throughput run")
    ap.add_argument("--presets", default="paper,cpu-mlp", help="the presets compared, sparse vs dense (comma list)")
    ap.add_argument("--body", default="anny", choices=["anny", "toy"],
                    help="the body of the batch (toy: the 2-joint sphere of the tests, no anny cache)")
    args = ap.parse_args(argv)
    device = torch.device(args.device)
    cuda = device.type == "cuda"
    rays_paper = args.rays_paper or (2048 if cuda else 48)
    rays_cpu = args.rays_cpu or (2048 if cuda else 192)

    t0 = time.perf_counter()
    template, M, feats, verts = rest_setup(args.body, 4)
    pose = {"anny": "anny reference pose (A-pose)", "toy": "toy sphere, unbent"}[args.body]
    results: dict[str, Any] = {"device": str(device), "torch": torch.__version__, "threads": torch.get_num_threads(),
                               "body": args.body, "joints": template.num_joints, "pose": pose,
                               "comparisons": []}
    if cuda:
        results["gpu"] = torch.cuda.get_device_name(device)
    rays = {"paper": rays_paper, "cpu-mlp": rays_cpu}
    presets = list(split_list(args.presets))
    if not presets or not set(presets) <= set(rays):
        ap.error(f"--presets {args.presets!r}: use paper, cpu-mlp or both")
    for preset in presets:
        batch = make_batch(M, feats, verts, rays[preset])
        results["comparisons"].append(compare(preset, template, batch, device, args.repeats))
    results["throughput"] = throughput(template, make_batch(M, feats, verts, args.rays_throughput, seed=1), device,
                                       args.steps)
    results["bench_s"] = time.perf_counter() - t0

    print(f"device {results['device']} ({results['threads']} threads), torch {results['torch']}, "
          f"{args.body} template ({template.num_joints} joints), 4 frames")
    print(f"{'preset':7} {'rays':>5} {'path':7} {'step s':>8} {'peak MB':>9} {'pairs':>10} {'max S_i':>8}")
    for c in results["comparisons"]:
        for path in ("sparse", "dense"):
            r = c[path]
            print(f"{c['preset']:7} {c['rays']:5d} {path:7} {r['step_s']:8.3f} {r['peak_bytes'] / 2**20:9.1f} "
                  f"{int(r['pairs']):10d} {int(r['max_node_samples']):8d}")
        print(f"{'':7} -> speedup {c['speedup']:.2f}x, memory -{100 * c['memory_reduction']:.1f}%, "
              f"{c['pairs_per_valid_sample']:.2f} nodes per non-empty sample, packing fill "
              f"{100 * c['packing_fill']:.0f}%, max |rgb sparse - dense| {c['max_abs_rgb_diff']:.1e}")
    tp = results["throughput"]
    print(f"training throughput (cpu preset, sparse, {tp['rays']} rays/step incl. Adam): {tp['rays_per_s']:.0f} rays/s "
          f"({tp['step_s']:.3f} s/step)")
    print(f"bench took {results['bench_s']:.0f} s")
    if args.out:
        from avatarctl.atomic import write_json

        write_json(args.out, results)
        print(f"wrote {args.out}")
    return results


if __name__ == "__main__":
    main()
