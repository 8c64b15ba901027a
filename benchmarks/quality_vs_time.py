"""Quality versus wall time of `avatarctl fit`, per backend (issue 12's benchmark; not a test).

For each backend (a name and `--set` overrides), the script copies the ingested project, runs `avatarctl fit` with
a time budget and snapshots after the given minutes of training (`FitConfig.snapshot_at_s`), scores every snapshot
with `avatarctl eval` (held-out views of training frames, bbox protocol, `--every 10`: the docs' protocol), and
times a 512x512 render (`--render-size`) of the final model. Fits run `--parallel` at a time with `--threads` threads each, so that
two 1-thread fits on the 2-core machine run under equal conditions (equal wall time, equal cores).

    python -m benchmarks.quality_vs_time PROJECT OUT --minutes 2,5,10 \
        --backend mlp= --backend "gaussians=model.field=gaussians" [--threads 1 --parallel 2]
        [--preset cpu-mlp] [--every 10] [--region garment] [--render-size 512] [--render-threads 2] [--reuse]

`--minutes` may be fractions (0.02 = 1.2 s: the test's toy run).

Writes OUT/results.csv, OUT/results.json and OUT/quality_vs_time.png (with matplotlib: `pip install -e .[bench]`).
Every figure names the protocol; the command line is stored in results.json.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from avatarctl.lists import split_list


def _run(cmd: list[str], threads: int, log: Path) -> subprocess.Popen:
    env = {**os.environ, "OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads)}
    return subprocess.Popen(cmd, env=env, stdout=log.open("w"), stderr=subprocess.STDOUT)


def _wait_all(procs: list[tuple[str, subprocess.Popen]]) -> dict[str, float]:
    """Wait for every process; return each one's peak RSS (GB) from wait4, and fail loudly on a non-zero exit."""
    peaks: dict[str, float] = {}
    for name, p in procs:
        _, status, usage = os.wait4(p.pid, 0)
        p.returncode = os.waitstatus_to_exitcode(status)
        if p.returncode != 0:
            raise SystemExit(f"{name}: exited with {p.returncode} (see its log in OUT)")
        peaks[name] = usage.ru_maxrss / 2**20  # KB -> GB
    return peaks


def _batched(items: list, n: int):
    for i in range(0, len(items), n):
        yield items[i:i + n]


def _fit_record(project: Path) -> dict:
    log = [json.loads(line) for line in (project / "fit" / "log.jsonl").read_text().splitlines()]
    loss_recs = [r for r in log if "loss" in r]
    if not loss_recs:
        raise SystemExit(f"{project}: the fit logged no step (it ran fewer than log_every steps): "
                         "give the backend a smaller log_every, e.g. --backend 'NAME=log_every=1'")
    last = loss_recs[-1]
    steps, seconds = last["step"], last["time"]
    stats = last.get("stats", {})
    window = loss_recs[len(loss_recs) // 2:]  # second half: steady-state throughput
    rays = sum(r["rays_per_s"] for r in window) / max(len(window), 1)
    return {"steps": steps, "fit_seconds": seconds, "steps_per_s": steps / max(seconds, 1e-9),
            "rays_per_s": rays, "hit_rays_per_step": stats.get("hit_rays"), "samples_per_step": stats.get("samples"),
            "evaluated_samples_per_step": stats.get("live_samples", stats.get("samples")),
            "pairs_per_step": stats.get("pairs")}


def _box_psnr(per_frame: Path) -> float:
    """Mean over the images of the per-image bbox PSNR (eval's per_frame.csv)."""
    with per_frame.open() as f:
        vals = [float(r["psnr"]) for r in csv.DictReader(f)]
    return sum(vals) / len(vals)


def _render_timing(project: Path, threads: int, side: int = 512) -> dict:
    """Time one render of `side` pixels on the long edge (the first held-out camera scaled, first training frame,
    posterior-mean latent) and one at the camera's own size -> render_<side>_s, _rays, _size, render_native_s, _size."""
    code = (
        "import json,sys,time,torch\n"
        "from avatarctl.project import Project\n"
        "from avatarctl.fit.checkpoint import load_avatar\n"
        "from avatarctl.render.engine import render_view\n"
        "av = load_avatar(Project.open(sys.argv[1]), device='cpu')\n"
        "cam0 = av.capture.cameras[av.capture.split.test_views[0]].pinhole()\n"
        "side = int(sys.argv[2])\n"
        "cam = cam0.scaled(side / max(cam0.width, cam0.height))\n"
        "cond = av.conditioning(av.capture.motion.for_frames([av.train_frames[0]]), frames_are_training=True)\n"
        "with torch.no_grad():\n"
        "    st = av.model.node_state(cond, mode='mean')\n"
        "    render_view(av.model, st, 0, cam0, av.fit_config.background)  # warm-up (kernel load)\n"
        "    t0 = time.perf_counter(); render_view(av.model, st, 0, cam0, av.fit_config.background)\n"
        "    native = time.perf_counter() - t0\n"
        "    t0 = time.perf_counter(); v = render_view(av.model, st, 0, cam, av.fit_config.background)\n"
        "print(json.dumps({f'render_{side}_s': time.perf_counter() - t0, f'render_{side}_rays': v.rays,\n"
        "                  f'render_{side}_size': [int(cam.width), int(cam.height)], 'render_native_s': native,\n"
        "                  'render_native_size': [int(cam0.width), int(cam0.height)]}))\n")
    env = {**os.environ, "OMP_NUM_THREADS": str(threads)}
    out = subprocess.run([sys.executable, "-c", code, str(project), str(side)], env=env, capture_output=True, text=True)
    if out.returncode != 0:
        raise SystemExit(f"render timing failed for {project}:\n{out.stderr[-2000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


@dataclass(frozen=True)
class QualityVsTime:
    """What `main` wrote: one row per (backend, snapshot) scored (the CSV's rows, the keys of its header)."""
    rows: tuple[dict, ...]
    csv: Path
    json: Path
    plot: Path | None  # None without matplotlib


def main(argv: list[str] | None = None) -> QualityVsTime:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("project", type=Path, help="an ingested project (e.g. of `avatarctl synth --preset small`)")
    ap.add_argument("out", type=Path)
    ap.add_argument("--backend", action="append", required=True,
                    help="'NAME=key=value key=value' (fit --set overrides, space-separated; empty: the preset)")
    ap.add_argument("--minutes", default="2,5,10", help="snapshot times, minutes of training")
    ap.add_argument("--preset", default="cpu-mlp",
                    help="the fit preset the backends' overrides apply to (cpu-mlp: the MLP fields, as the commands in "
                         "docs/ were run when it was called cpu; a backend model.field=gaussians is the cpu preset)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--parallel", type=int, default=2, help="fits / evals run at the same time")
    ap.add_argument("--every", type=int, default=10, help="eval: keep every N-th training frame")
    ap.add_argument("--region", default=None, help="eval --region (e.g. garment): region PSNRs in the table")
    ap.add_argument("--render-size", type=int, default=512, help="the timed render's long edge, pixels")
    ap.add_argument("--render-threads", type=int, default=2, help="threads of the render timing (run alone)")
    ap.add_argument("--reuse", action="store_true",
                    help="keep backends whose OUT/NAME/project already holds a finished fit (no re-fit, no re-eval)")
    args = ap.parse_args(argv)

    minutes = list(split_list(args.minutes, float))
    backends = []
    for spec in args.backend:
        name, _, sets = spec.partition("=")
        backends.append((name, sets.split()))
    args.out.mkdir(parents=True, exist_ok=True)
    exe = [sys.executable, "-m", "avatarctl"]  # this interpreter's avatarctl, on PATH or not

    # 1. fits, `parallel` at a time
    projects, done = {}, set()
    for name, _ in backends:
        p = args.out / name / "project"
        projects[name] = p
        if args.reuse and (p / "fit" / "checkpoints" / "latest.pt").exists():
            done.add(name)
            continue
        if p.exists():
            shutil.rmtree(p)
        p.mkdir(parents=True)
        shutil.copytree(args.project / "ingest", p / "ingest")
        shutil.copy(args.project / "project.json", p / "project.json")
    peaks: dict[str, float] = {}
    peaks_file = args.out / "fit_peak_rss_gb.json"
    if peaks_file.exists():
        peaks.update(json.loads(peaks_file.read_text()))
    for batch in _batched([b for b in backends if b[0] not in done], args.parallel):
        procs = []
        for name, sets in batch:
            cmd = [*exe, "fit", str(projects[name]), "--preset", args.preset, "--iters", "10000000",
                   "--set", f"time_budget_s={max(minutes) * 60:g}",
                   "--set", "snapshot_at_s=" + ",".join(f"{m * 60:g}" for m in minutes),
                   "--set", "val_every=0", "--set", "val_pairs=0", "--set", "checkpoint_every=100000"]
            for s in sets:
                cmd += ["--set", s]
            print(f"fit {name}: {' '.join(cmd)}", flush=True)
            procs.append((name, _run(cmd, args.threads, args.out / name / "fit.log")))
        peaks.update(_wait_all(procs))
        peaks_file.write_text(json.dumps(peaks))

    # 2. evals of every snapshot
    jobs = []
    for name, _ in backends:
        for m in minutes:
            snap = projects[name] / "fit" / "checkpoints" / f"snapshot_{int(round(m * 60)):05d}s.pt"
            if snap.exists() and not (projects[name] / "eval" / f"t{m:g}min" / "metrics.json").exists():
                jobs.append((name, m, snap))
    for batch in _batched(jobs, args.parallel):
        procs = []
        for name, m, snap in batch:
            cmd = [*exe, "eval", str(projects[name]), "--split", "novel_view", "--protocol", "bbox",
                   "--every", str(args.every), "--checkpoint", str(snap), "--name", f"t{m:g}min", "--sheet", "4"] \
                + (["--region", args.region] if args.region else [])
            procs.append((f"{name}@{m:g}", _run(cmd, args.threads, args.out / name / f"eval_t{m:g}.log")))
        _wait_all(procs)

    # 3. render timing (alone on the machine) and the table
    rows = []
    for name, sets in backends:
        rec = _fit_record(projects[name])
        rec.update(_render_timing(projects[name], threads=args.render_threads, side=args.render_size))
        for m in minutes:
            mfile = projects[name] / "eval" / f"t{m:g}min" / "metrics.json"
            if not mfile.exists():
                continue
            met = json.loads(mfile.read_text())
            box = _box_psnr(mfile.parent / "per_frame.csv")  # with --region, metrics.json's headline is the region
            regions = {f"{k}_psnr": v["psnr"] for k, v in (met.get("regions") or {}).items()}
            regions.update({f"{k}_flat_colour_psnr": v.get("flat_colour_psnr")
                            for k, v in (met.get("regions") or {}).items()})
            rows.append({"backend": name, "overrides": " ".join(sets), "minutes": m,
                         "psnr_bbox": box, "ssim_bbox": met["ssim"], "images": met["images"], **regions,
                         "sheet": str(projects[name] / "eval" / f"t{m:g}min" / "sheet.png"),
                         "fit_peak_rss_gb": round(peaks.get(name, float("nan")), 3), **rec})
    if not rows:
        raise SystemExit(f"no snapshot was scored: see the fit and eval logs under {args.out}")
    with (args.out / "results.csv").open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    meta = {"command": " ".join([sys.executable, "-m", "benchmarks.quality_vs_time"] + (argv or sys.argv[1:])),
            "protocol": "held-out views of training frames (split novel_view), bbox protocol (Neural Body box), "
                        f"every {args.every}th training frame, posterior-mean latent; full-resolution images",
            "threads_per_fit": args.threads, "parallel": args.parallel, "date": time.strftime("%Y-%m-%d %H:%M"),
            "rows": rows}
    (args.out / "results.json").write_text(json.dumps(meta, indent=1))
    plot = _plot(rows, args.out / "quality_vs_time.png", meta["protocol"])
    for r in rows:
        print(f"{r['backend']:>14} {r['minutes']:>5g} min  PSNR {r['psnr_bbox']:.2f} dB  SSIM {r['ssim_bbox']:.3f}  "
              f"{r['steps_per_s']:.2f} steps/s  {r['rays_per_s']:.0f} rays/s  "
              f"{args.render_size}² render {r[f'render_{args.render_size}_s']:.3f} s")
    return QualityVsTime(rows=tuple(rows), csv=args.out / "results.csv", json=args.out / "results.json", plot=plot)


def _region_names(rows: list[dict]) -> list[str]:
    """The eval regions the rows were scored by (`--region`: e.g. garment, body), in their first row's order."""
    return [k[:-len("_psnr")] for k in rows[0] if k.endswith("_psnr") and k != "psnr_bbox"
            and not k.endswith("_flat_colour_psnr")]


def _plot(rows: list[dict], path: Path, protocol: str) -> Path | None:
    """PSNR against minutes of fit, one line per backend: the bbox PSNR, then one panel per region (`--region`) with
    the region's flat-colour PSNR (what a single colour would score there) in its title, and as a dashed line where it
    lies within 2 dB of the curves."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib not installed (pip install -e .[bench]): no plot written")
        return None
    regions = _region_names(rows)
    fig, axes = plt.subplots(1, 1 + len(regions), figsize=(7 + 4.5 * len(regions), 4.5), squeeze=False)
    panels = [("psnr_bbox", "held-out-view PSNR (bbox) vs fit time")] + [
        (f"{r}_psnr", f"{r} region") for r in regions]
    for ax, (key, title) in zip(axes[0], panels):
        low = math.inf
        for name in dict.fromkeys(r["backend"] for r in rows):
            pts = sorted((r["minutes"], r[key]) for r in rows if r["backend"] == name and r.get(key) is not None)
            ax.plot([p[0] for p in pts], [p[1] for p in pts], marker="o", label=name)
            low = min([low] + [p[1] for p in pts])
        flat = rows[0].get(key.replace("_psnr", "_flat_colour_psnr")) if key != "psnr_bbox" else None
        if flat is not None:
            title += f" (flat colour {flat:.2f} dB)"
            if flat > low - 2:
                ax.axhline(flat, color="grey", linestyle="--", linewidth=1, label="flat colour")
        ax.set_xlabel("minutes of fit (wall time)")
        ax.set_ylabel("PSNR (dB)")
        ax.set_title(title, fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.text(0.01, 0.01, protocol, fontsize=6)
    fig.tight_layout(rect=(0, 0.04, 1, 1))
    tmp = path.with_suffix(".tmp.png")
    fig.savefig(tmp, dpi=120)
    plt.close(fig)
    os.replace(tmp, path)
    return path


if __name__ == "__main__":
    main()
