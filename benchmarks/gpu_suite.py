"""Every GPU measurement of the Gaussian local fields in one script (issue 28): run it in one call of a lent GPU.

    python -m benchmarks.gpu_suite --out OUT [--device cuda] [--quick]

Parts (each timed, each a section of OUT/gpu_suite.json; a part that fails is recorded and the rest still run):
1. `env`: torch / warp versions, the device's name.
2. `parity`: the rasterizer on the device against the CPU (the same random scene, forward and gradients), and a
   whole avatar render (`SlrfAvatar` with `model.field = "gaussians"`, same weights) device vs CPU.
3. `raster`: `benchmarks.splat_bench` on the device (ms per forward / backward, 256² and 512², 20k / 50k Gaussians).
4. `train`: training throughput of the avatar at 512²: full images per second of a whole training step (node state
   with the cVAE posterior, posed Gaussians, rasterize B full 512² images, L1 + D-SSIM + mask loss, backward, Adam).
   The body is the toy sphere template (`body/toy.py`, a 1 m sphere filling a 512² view from 3 m) with the `cpu`
   preset's 128 nodes x `model.gaussians.per_node` Gaussians, since anny's model cache cannot be built on a bare GPU
   machine in a lease; the cost per image depends on the Gaussians' number and screen size, not on the body.
5. `render`: ms per 512² render of that avatar in eval mode (`render.engine.render_view`, the path of render /
   eval / view), mean of 20 after 3 warm-ups.
6. `profile`: torch.profiler over 5 such renders: the top operators by device and by host time, and the count of
   host-device synchronisations per render.
7. `track`: the garment tracker (`fit/garment_track.py`: the reference surface's stereo, then `track`) on a
   timing scene (a tube of 30 rings 2 cm apart, 72 vertices a ring, in 8 views of 512², 7 frames of random noise,
   the stop rule off) on the device and on the CPU: seconds each, and the largest distance between their tracked
   vertices (on noise there is no true surface, so the solves drift apart with the devices' summation orders: a
   diagnostic, not parity; the tracker's parity is `tests/test_garment_track.py`'s CUDA test).

`--quick`: tiny sizes, so the script itself runs in the CPU test suite (tests/test_gpu_suite.py) and cannot rot.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
import traceback
from pathlib import Path
from typing import Any, Callable

from avatarctl.lists import split_list


def _sync(device: str) -> None:
    import torch

    if device.startswith("cuda"):
        torch.cuda.synchronize()


def _timed(fn: Callable[[], Any], device: str, repeats: int, warmup: int = 2) -> float:
    """Mean seconds of `fn` over `repeats` calls after `warmup` calls."""
    for _ in range(warmup):
        fn()
    _sync(device)
    t0 = time.perf_counter()
    for _ in range(repeats):
        fn()
    _sync(device)
    return (time.perf_counter() - t0) / repeats


def _toy_avatar(device: str, per_node: int, nodes: int, seed: int = 0, frames: int = 4):
    """A Gaussian-field avatar on a 1 m toy sphere, with its conditioning for `frames` training frames."""
    import torch

    from avatarctl.body.toy import sphere_template, toy_joint_transforms
    from avatarctl.model.avatar import FrameConditioning, SlrfAvatar
    from avatarctl.fit.config import preset

    template = sphere_template(num_vertices=max(4 * nodes, 400), radius=0.5)
    cfg = preset("cpu").model.with_(field="gaussians", num_nodes=nodes, hull={"nodes": 0},
                                    pose_refine={"enabled": False}).with_cvae_width_for(train_views=2)  # multi-view
    cfg = cfg.with_(gaussians=cfg.gaussians.__class__(per_node=per_node))
    torch.manual_seed(seed)
    model = SlrfAvatar(cfg, template, num_frames=frames, seed=seed)
    bend = torch.linspace(0.0, 0.6, frames)
    M, feats = toy_joint_transforms(bend)
    cond = FrameConditioning(M, feats, torch.linspace(0, 1, frames), torch.arange(frames))
    return model.to(device), cond.to(device)


def _camera(size: int):
    """A camera 3 m in front of the sphere, its 1 m filling about 60 % of the image."""
    import numpy as np

    from avatarctl.geometry.cameras import Camera

    f = 1.8 * size
    return Camera(name="bench", K=np.array([[f, 0, (size - 1) / 2], [0, f, (size - 1) / 2], [0, 0, 1]]),
                  R=np.eye(3), T=np.array([0.0, 0.0, 3.0]), width=size, height=size)


def part_env(device: str) -> dict:
    import torch
    import warp as wp

    out = {"torch": torch.__version__, "warp": wp.config.version, "python": platform.python_version(),
           "device": device}
    if device.startswith("cuda"):
        out["gpu"] = torch.cuda.get_device_name(0)
    return out


def part_parity(device: str, quick: bool) -> dict:
    import torch

    from avatarctl.render.engine import render_view
    from avatarctl.splat import SplatCamera, rasterization

    gen = torch.Generator().manual_seed(0)
    G, size = (200, 48) if quick else (5000, 256)
    means = torch.randn(G, 3, generator=gen) * 0.3
    A = torch.randn(G, 3, 3, generator=gen) * 0.02
    covars = A @ A.transpose(1, 2) + 1e-5 * torch.eye(3)
    colors = torch.rand(G, 3, generator=gen)
    opac = torch.rand(G, generator=gen) * 0.9
    cam = SplatCamera.from_camera(_camera(size))
    bg = torch.tensor([0.1, 0.2, 0.3])
    res: dict[str, Any] = {}
    outs = {}
    for dev in ("cpu", device):
        m, c, o = (t.detach().to(dev).clone().requires_grad_() for t in (means, colors, opac))
        rgb, alpha, _ = rasterization(m, covars.to(dev), c, o, [cam.to(dev)], bg.to(dev))
        (rgb * torch.linspace(0, 1, 3, device=dev)).sum().backward()
        outs[dev] = [t.detach().cpu() for t in (rgb, alpha, m.grad, c.grad, o.grad)]
    for name, a, b in zip(("rgb", "alpha", "grad_means", "grad_colors", "grad_opacities"), outs["cpu"], outs[device]):
        res[f"raster_{name}_max_abs_diff"] = float((a - b).abs().max())
        res[f"raster_{name}_max_abs"] = float(a.abs().max())
    model, cond = _toy_avatar("cpu", 8 if quick else 64, 16 if quick else 128)
    model.eval()
    views = {}
    for dev in ("cpu", device):
        m = model.to(dev)
        with torch.no_grad():
            state = m.node_state(cond.to(dev), "mean")
        views[dev] = render_view(m, state, 1, _camera(size), (0.0, 0.0, 0.0)).rgb
    res["avatar_render_max_abs_diff"] = float(abs(views["cpu"] - views[device]).max())
    return res


def part_raster(device: str, quick: bool) -> dict:
    from benchmarks.splat_bench import run

    sizes = [(64, 500)] if quick else [(256, 20_000), (256, 50_000), (512, 50_000)]
    return {"table": run(device, sizes)}


def part_train(device: str, quick: bool) -> dict:
    """Images per second of whole training steps, with 4 images per step (the cpu preset's batch) and with 16."""
    import torch

    from avatarctl.model.densify import relocate_dead
    from avatarctl.splat import SplatCamera

    size, per_node, nodes, steps = (48, 8, 16, 3) if quick else (512, 192, 128, 30)
    out: dict[str, Any] = {"image_size": size, "gaussians": nodes * per_node}
    for batch in (4, 16):
        model, cond = _toy_avatar(device, per_node, nodes, frames=batch)
        model.train()
        opt = torch.optim.Adam(model.parameters(), lr=5e-4)
        cam = SplatCamera.from_camera(_camera(size), device=device)
        gen = torch.Generator(device=device).manual_seed(0)
        target = [torch.rand(size, size, 3, device=device, generator=gen) for _ in range(batch)]
        mask = [torch.ones(size, size, device=device) for _ in range(batch)]
        bg = torch.zeros(3, device=device)

        def step() -> None:
            state = model.node_state(cond, "posterior", generator=gen)
            posed = model.posed_gaussians(state)
            rgb, alpha = model.render_images(posed, [cam] * batch, bg)  # as fit.steps.render_crops
            terms = model.image_losses(rgb, alpha, target, mask, state)
            opt.zero_grad(set_to_none=True)
            terms.total.backward()
            opt.step()

        if device.startswith("cuda"):
            torch.cuda.reset_peak_memory_stats()
        sec = _timed(step, device, steps)
        relocate_dead(model.fields, opt, 0.005, 0, 100)  # the density control runs on the device too
        _sync(device)
        out[f"batch{batch}"] = {"seconds_per_step": sec, "images_per_s": batch / sec,
                                "pixels_per_s": batch * size * size / sec,
                                "peak_gpu_gb": torch.cuda.max_memory_allocated() / 2**30
                                if device.startswith("cuda") else None}
    return out


def _eval_avatar(device: str, quick: bool):
    """(model in eval mode, its node state of frame 0 with the posterior mean, a camera): what `part_render` and
    `part_profile` render (512² and 128 x 192 Gaussians; tiny with `quick`)."""
    import torch

    size, per_node, nodes = (48, 8, 16) if quick else (512, 192, 128)
    model, cond = _toy_avatar(device, per_node, nodes)
    model.eval()
    with torch.no_grad():
        state = model.node_state(cond, "mean")
    return model, state, _camera(size)


def part_render(device: str, quick: bool) -> dict:
    import torch

    from avatarctl.render.engine import render_view

    model, state, cam = _eval_avatar(device, quick)
    size, reps = cam.width, 3 if quick else 20
    sec = _timed(lambda: render_view(model, state, 0, cam, (0.0, 0.0, 0.0)), device, reps, 3)
    # where the time goes: posing (decoder, covariances), colours + projection + binning, the raster kernel; the
    # fused projection (what render_view uses) beside the pure-torch pair it replaces
    from avatarctl.splat import SplatCamera
    from avatarctl.splat.project import project_gaussians
    from avatarctl.splat.rasterizer import Canvas, bin_gaussians, project_and_reach, rasterize, reach

    scam = SplatCamera.from_camera(cam, device=device)
    bg = torch.zeros(3, device=device)
    with torch.no_grad():
        posed = model.posed_gaussians(state)
        m, c, o = posed.means[:1], posed.covars[:1], posed.opacities[:1]  # [1, G, ...]: one image
        proj = project_and_reach(m, c, o, [scam])
        flat = Canvas.of(proj, [(size, size)]).proj
        colors = posed.colors(0, scam.center)[None]
        parts = {"pose_ms": _timed(lambda: model.posed_gaussians(state), device, reps),
                 "project_reach_fused_ms": _timed(lambda: project_and_reach(m, c, o, [scam]), device, reps),
                 "project_torch_ms": _timed(lambda: project_gaussians(m, c, [scam]), device, reps),
                 "reach_torch_ms": _timed(lambda: reach(flat, o[0], size, size), device, reps),
                 "bin_ms": _timed(lambda: bin_gaussians(flat, o[0], size, size), device, reps),
                 "raster_ms": _timed(lambda: rasterize(proj, colors, o, [(size, size)], bg), device, reps)}
    return {"image_size": size, "gaussians": int(posed.means.shape[1]), "ms_per_render": 1e3 * sec,
            **{k: 1e3 * v for k, v in parts.items()}}


def part_density(device: str, quick: bool) -> dict:
    """The Gaussians as a density at points (`splat.density`, what the mesh export samples): the posed toy avatar
    queried at points around its nodes, ms per million points, and the largest relative difference of sigma against
    the dense torch twin on CPU (a subset of the points)."""
    import torch

    from avatarctl.splat.density import gaussian_field_at, gaussian_field_at_torch

    model, state, _ = _eval_avatar(device, quick)
    n_points, reps = (2_000, 2) if quick else (1_000_000, 5)
    gen = torch.Generator().manual_seed(0)
    with torch.no_grad():
        posed = model.posed_gaussians(state)
        centers = state.centers[0].cpu()
        pts = centers[torch.randint(centers.shape[0], (n_points,), generator=gen)]
        pts = (pts + 0.05 * torch.randn(n_points, 3, generator=gen)).to(device)
        dirs = torch.nn.functional.normalize(torch.randn(n_points, 3, generator=gen), dim=-1).to(device)
        args = (posed.means[0], posed.covars[0], posed.opacities[0] * 50.0, posed.sh[0])
        sec = _timed(lambda: gaussian_field_at(pts, dirs, *args), device, reps)
        _, sigma = gaussian_field_at(pts[:500], dirs[:500], *args)
        _, ref = gaussian_field_at_torch(pts[:500].cpu().double(), dirs[:500].cpu().double(),
                                         *(a.cpu().double() for a in args))
    rel = float(((sigma.cpu().double() - ref).abs() / ref.clamp(min=1e-3)).max())
    return {"points": n_points, "gaussians": int(posed.means.shape[1]),
            "ms_per_million_points": 1e3 * sec / n_points * 1e6, "sigma_max_rel_diff_vs_twin": rel}


def part_profile(device: str, quick: bool) -> dict:
    """Where a render's time goes on the device: torch.profiler's top operators by self device time and by self host
    time, and the count of host-device synchronisations (what keeps a small render from its kernels' speed)."""
    from torch.profiler import ProfilerActivity, profile

    from avatarctl.render.engine import render_view

    model, state, cam = _eval_avatar(device, quick)
    for _ in range(3):
        render_view(model, state, 0, cam, (0.0, 0.0, 0.0))
    _sync(device)
    acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.startswith("cuda") else [])
    with profile(activities=acts) as prof:
        for _ in range(5):
            render_view(model, state, 0, cam, (0.0, 0.0, 0.0))
        _sync(device)
    events = prof.key_averages()

    def top(key: str, n: int = 25) -> list[dict]:
        rows = sorted(events, key=lambda e: getattr(e, key, 0.0) or 0.0, reverse=True)[:n]
        return [{"name": e.key, "count": e.count, "self_cpu_ms": e.self_cpu_time_total / 1e3 / 5,
                 "self_device_ms": (getattr(e, "self_device_time_total", 0.0) or 0.0) / 1e3 / 5} for e in rows]

    syncs = {e.key: e.count / 5 for e in events
             if any(s in e.key for s in ("Synchronize", "Memcpy", "aten::item", "aten::_local_scalar_dense",
                                         "aten::nonzero", "cudaLaunchKernel"))}
    return {"per_render": {"by_device_time": top("self_device_time_total"), "by_cpu_time": top("self_cpu_time_total"),
                           "sync_like_calls": syncs}}


def part_track(device: str, quick: bool) -> dict:
    """Part 7 of the module docstring."""
    import cv2
    import numpy as np

    from avatarctl.fit import garment_track as gt
    from avatarctl.geometry.cameras import Camera, look_at

    size, views, frames, rings, segments = (48, 3, 3, 4, 12) if quick else (512, 8, 7, 30, 72)
    a = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    z = np.arange(rings) * 0.02
    A, Z = np.meshgrid(a, z)
    tube = np.stack([0.3 * np.cos(A), 0.3 * np.sin(A), Z], -1).reshape(-1, 3)
    faces = gt.tube_faces(rings, segments)
    body = np.array([[0.05 * x, 0.05 * y, h] for x in (-1, 1) for y in (-1, 1) for h in (0.0, z[-1])])
    body_faces = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1], [2, 3, 7], [2, 7, 6],
                           [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    cams = []
    for c in range(views):
        t = 2 * np.pi * c / views
        R, T = look_at(np.array([2.5 * np.cos(t), 2.5 * np.sin(t), 0.6]), np.array([0.0, 0.0, z[-1] / 2]))
        f = 2.2 * size
        cams.append(Camera(f"c{c}", np.array([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1]]), R, T, size, size))
    rng = np.random.default_rng(0)
    noise = {(c, k): (cv2.GaussianBlur(rng.random((size, size, 3)).astype(np.float32), (0, 0), 2) * 255).astype(
        np.uint8) for c in range(views) for k in range(frames)}
    eye = np.broadcast_to(np.eye(4), (1, 4, 4))
    inp = gt.TrackingInput(frames=tuple(range(frames)), cameras=tuple(cams), image=lambda c, k: noise[(c, k)],
                           mask=lambda c, k: np.ones((size, size), bool), body_vertices=np.stack([body] * frames),
                           body_faces=body_faces, body_transforms=lambda fi, v: np.repeat(eye, len(v), 0),
                           up=np.tile([0.0, 0.0, 1.0], (frames, 1)))
    mesh = gt.GarmentMesh(tube, faces, frame=frames // 2, segments=segments)
    settings = gt.TrackSettings(iters=5, stereo_iters=5) if quick else gt.TrackSettings()
    out, seconds = {}, {}
    for dev in dict.fromkeys([device, "cpu"]):
        t0 = time.perf_counter()
        ref = gt.refine_reference(inp, mesh, frames // 2, settings, device=dev)
        out[dev] = gt.track(inp, ref, frames // 2, settings, stop=False, device=dev).vertices
        _sync(dev)
        seconds[dev] = time.perf_counter() - t0
    return {"vertices": len(tube), "frames": frames, "views": views, "size": size,
            "seconds_by_device": {k: round(v, 2) for k, v in seconds.items()},
            "max_vertex_diff_mm_vs_cpu": float(np.abs(out[device] - out["cpu"]).max() * 1e3)}


PARTS = {"env": part_env, "parity": part_parity, "raster": part_raster, "train": part_train, "render": part_render,
         "density": part_density, "profile": part_profile, "track": part_track}


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--quick", action="store_true", help="tiny sizes (the CPU test of this script)")
    ap.add_argument("--parts", default=",".join(PARTS))
    a = ap.parse_args(argv)
    a.out.mkdir(parents=True, exist_ok=True)
    results: dict[str, Any] = {"command": " ".join(["python -m benchmarks.gpu_suite"] + (argv or [])), "parts": {}}
    for name in split_list(a.parts):
        t0 = time.perf_counter()
        try:
            fn = PARTS[name]
            out = fn(a.device) if name == "env" else fn(a.device, a.quick)
            results["parts"][name] = {"ok": True, **out}
        except Exception as e:  # recorded, the other parts still run
            results["parts"][name] = {"ok": False, "error": f"{type(e).__name__}: {e}",
                                      "traceback": traceback.format_exc()[-3000:]}
        results["parts"][name]["seconds"] = round(time.perf_counter() - t0, 2)
        print(f"[gpu_suite] {name}: {json.dumps(results['parts'][name], default=str)[:1500]}", flush=True)
        (a.out / "gpu_suite.json").write_text(json.dumps(results, indent=2, default=str))
    return results


if __name__ == "__main__":
    main()
