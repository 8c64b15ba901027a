"""Speed of the Gaussian splatting rasterizer (`avatarctl.splat.rasterization`): ms per forward (projection, binning,
compositing), backward and both, on a body-like scene, with one thread and with every core.

The scene: G random Gaussians uniform in a 0.5 x 1.7 x 0.3 m box (a standing person) seen from 3 m by a square camera
whose image the box fills; scales log-uniform 0.4-3 cm per axis, random rotations, opacities sigmoid(N(1, 1.5)),
random colours: what a fitted avatar's Gaussians look like from a training view. Times are medians over
`--repeats` after one warm-up (which builds the Warp kernels on a fresh cache). On CPU the rasterizer shares the
tiles among `torch.get_num_threads()` threads: the rows with threads 1 and N compare one core with N.

    python -m benchmarks.splat_bench [--device cpu|cuda] [--sizes 256:20000 256:50000 512:50000]
                                     [--threads 1 2] [--backends warp] [--frozen colors] [--repeats 5] [--json OUT]

`--frozen` names inputs (means, covars, colors, opacities) that take no gradient, as a caller that trains only
some of them: the backward then computes only the gradients required. The rasterizer's backward alone (CPU time, one
thread, 256^2 and 512^2 / 50k, 2026-11-29): all four 45.5 / 130.9 ms, colours frozen 42.7 / 124.6 (-5 %), only the
colours trained 35.9 / 99.6 (-22 %); before it computed all four whatever was asked (45-46 / 128-142 ms each way).

Measured (2026-11-26, commit "CPU binning by a bucket sort", the lent H200 machine: idle Xeon cores, warp 1.19.0,
torch 2.11; ms per call, medians of 11 / 20; total = forward + backward, projection included):

    256^2 / 20k    CPU 1 thread 121.8, 2 threads 70.2, 4 threads 47.4    H200 11.2
    256^2 / 50k    CPU 1 thread 188.2, 2 threads 102.3, 4 threads 64.7   H200 11.0
    512^2 / 50k    CPU 1 thread 427.9, 2 threads 222.1, 4 threads 129.5  H200 10.5

The same code measured 76-90 ms (256^2 / 20k, one thread) on earlier machines of that kind: compare rows of one run
only. The scene is deep (a filled box: ~35 splats per pixel over the image, ~0.9 M of 2.3 M splat-pixel pairs
composited before the pixels end), hence slower than a surface-only avatar. On the CPU the pixel walk (the GPU
variant) takes 4.2x the tile walk (351 vs 85 ms). On CUDA the time is mostly launch overhead: projection and
binning (~50 small torch ops) take ~5-6 ms, the forward's compositing ~1.4 ms on top.
Two cores: Warp's CPU launch is a ctypes call that releases the GIL (a Python thread runs on during a launch; two
launches from two threads use two cores), so the tiles are split among torch.get_num_threads() threads: 1.7-1.9x
with 2, 2.6-3.3x with 4 on idle cores. On a 2-core machine busy with other jobs, torch.set_num_threads(2) made the
torch part (projection, binning) ~5x slower (OpenMP barriers wait for a descheduled thread) and the whole step 2-2.6x
slower than one thread: set one torch thread there.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

DEFAULT_SIZES = ((256, 20_000), (256, 50_000), (512, 50_000))  # (image side, Gaussians)


def body_scene(n: int, side: int, device: str = "cpu", seed: int = 0):
    """n Gaussians in a person-sized box seen from 3 m -> (means [n, 3], covars [n, 3, 3], colors [n, 3],
    opacities [n], SplatCamera side x side)."""
    import torch

    from avatarctl.splat import SplatCamera

    gen = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=gen) - 0.5) * torch.tensor([0.5, 1.7, 0.3])
    scales = torch.exp(torch.empty(n, 3).uniform_(float(torch.log(torch.tensor(0.004))),
                                                  float(torch.log(torch.tensor(0.03))), generator=gen))
    q = torch.nn.functional.normalize(torch.randn(n, 4, generator=gen), dim=-1)
    w, x, y, z = q.unbind(-1)
    rot = torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                       2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                       2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1).reshape(n, 3, 3)
    A = rot * scales[:, None, :]
    covars = A @ A.transpose(-1, -2)
    colors = torch.rand(n, 3, generator=gen)
    opacities = torch.sigmoid(1.0 + 1.5 * torch.randn(n, generator=gen))
    f = side * 3.0 / 1.9  # the 1.7 m box plus a margin fills the image from 3 m
    K = torch.tensor([[f, 0.0, (side - 1) / 2], [0.0, f, (side - 1) / 2], [0.0, 0.0, 1.0]])
    cam = SplatCamera(K=K, R=torch.eye(3), T=torch.tensor([0.0, 0.0, 3.0]), width=side, height=side)
    return (means.to(device), covars.to(device), colors.to(device), opacities.to(device), cam.to(device))


INPUTS = ("means", "covars", "colors", "opacities")


def _time_case(side: int, n: int, device: str, backend: str, repeats: int, frozen: tuple[str, ...] = ()) -> dict:
    import torch

    from avatarctl.splat import rasterization
    from avatarctl.splat.project import project_gaussians
    from avatarctl.splat.rasterizer import Canvas, bin_gaussians

    means, covars, colors, opacities, cam = body_scene(n, side, device)
    background = torch.ones(3, device=device)
    inputs = dict(zip(INPUTS, (means, covars, colors, opacities)))
    leaves = [t.requires_grad_() for name, t in inputs.items() if name not in frozen]
    g_rgb = torch.rand(side, side, 3, generator=torch.Generator().manual_seed(1)).to(device)
    g_alpha = torch.rand(side, side, generator=torch.Generator().manual_seed(2)).to(device)

    def sync():
        if device.startswith("cuda"):
            torch.cuda.synchronize()

    fwd, bwd, prep = [], [], []
    for i in range(repeats + 1):
        for t in leaves:
            t.grad = None
        sync()
        t0 = time.perf_counter()
        with torch.no_grad():  # the torch projection (the fused one has no backward) and the binning alone
            canvas = Canvas.of(project_gaussians(means[None], covars[None], [cam]), [(side, side)])
            bins = bin_gaussians(canvas.proj, opacities, side, side)
        sync()
        t1 = time.perf_counter()
        rgb, alpha, meta = rasterization(means, covars, colors, opacities, [cam], background, backend=backend)
        sync()
        t2 = time.perf_counter()
        torch.autograd.backward([rgb[0], alpha[0]], [g_rgb, g_alpha])
        sync()
        t3 = time.perf_counter()
        if i:  # the first is the warm-up
            prep.append(t1 - t0)
            fwd.append(t2 - t1)
            bwd.append(t3 - t2)
    med = lambda v: 1e3 * sorted(v)[len(v) // 2]  # noqa: E731
    visible = int((meta.radii > 0).sum())
    return {"side": side, "gaussians": n, "visible": visible, "tile_entries": int(bins.ids.shape[0]),
            "backend": backend, "frozen": list(frozen),
            "threads": torch.get_num_threads() if device == "cpu" else None,
            "project_bin_ms": med(prep), "forward_ms": med(fwd), "backward_ms": med(bwd),
            "total_ms": med([a + b for a, b in zip(fwd, bwd)]), "repeats": repeats}


def run(device: str = "cpu", sizes=DEFAULT_SIZES, threads=None, backends=("warp",), repeats: int = 5,
        frozen: tuple[str, ...] = ()) -> dict:
    """Time every (size, backend, thread count) -> {"device", "host", "rows": [...]}; sizes: (side, Gaussians).
    threads: CPU thread counts (default 1 and every core); ignored on CUDA. frozen: inputs without gradient."""
    unknown = sorted(set(frozen) - set(INPUTS))
    if unknown or len(frozen) == len(INPUTS):
        raise ValueError(f"frozen: {unknown or list(frozen)} is not a proper subset of {', '.join(INPUTS)}")
    import torch

    saved = torch.get_num_threads()
    if threads is None:
        threads = sorted({1, os.cpu_count() or 1})
    rows = []
    try:
        for side, n in sizes:
            for backend in backends:
                for k in (threads if device == "cpu" else [saved]):
                    torch.set_num_threads(k)
                    rows.append(_time_case(side, n, device, backend, repeats, tuple(frozen)))
    finally:
        torch.set_num_threads(saved)
    name = torch.cuda.get_device_name() if device.startswith("cuda") else platform.processor() or platform.machine()
    return {"device": device, "device_name": name, "cpu_count": os.cpu_count(), "rows": rows}


def table(result: dict) -> str:
    """The rows as a fixed-width table."""
    head = (f"{'image':>7} {'gaussians':>9} {'visible':>7} {'entries':>8} {'backend':>10} {'threads':>7} "
            f"{'proj+bin':>9} {'forward':>9} {'backward':>9} {'total':>9}")
    frozen = sorted({f for r in result["rows"] for f in r.get("frozen", [])})
    lines = [f"device: {result['device']} ({result['device_name']}), ms per call (median)"
             + (f"; no gradient for {', '.join(frozen)}" if frozen else ""), head]
    for r in result["rows"]:
        lines.append(f"{r['side']:>5}^2 {r['gaussians']:>9} {r['visible']:>7} {r['tile_entries']:>8} "
                     f"{r['backend']:>10} {str(r['threads'] or '-'):>7} {r['project_bin_ms']:>9.1f} "
                     f"{r['forward_ms']:>9.1f} {r['backward_ms']:>9.1f} {r['total_ms']:>9.1f}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict:
    """The command line -> `run`'s result (also printed as a table, and written with `--json`)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--sizes", nargs="+", default=[f"{s}:{n}" for s, n in DEFAULT_SIZES],
                    help="SIDE:GAUSSIANS pairs")
    ap.add_argument("--threads", type=int, nargs="+", default=None, help="CPU thread counts (default: 1 and all)")
    ap.add_argument("--backends", nargs="+", default=["warp"], help="warp, warp_tile, warp_pixel, torch")
    ap.add_argument("--frozen", nargs="*", default=[], choices=INPUTS, help="inputs that take no gradient")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--json", type=Path, default=None, help="write the results as JSON here")
    args = ap.parse_args(argv)
    sizes = [tuple(int(v) for v in s.split(":")) for s in args.sizes]
    result = run(args.device, sizes, args.threads, tuple(args.backends), args.repeats, tuple(args.frozen))
    print(table(result))
    if args.json:
        args.json.write_text(json.dumps(result, indent=2))
    return result


if __name__ == "__main__":
    main()
