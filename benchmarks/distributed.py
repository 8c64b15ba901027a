"""Benchmark: data-parallel fit throughput (steps/s, rays/s) on N = 1, 2 ranks of this machine.

    python -m benchmarks.distributed [--project DIR] [--seconds 20] [--preset cpu-mlp] [--out bench_dist.json]
        [--parts wall,cpu,phases,sync] [--ranks 1,2] [--cpu-steps 20]

(run from the repository root: `benchmarks/` is not part of the installed package).

Project: an ingested project (`--project`), else `avatarctl synth --preset tiny` + `ingest` into a cache folder
(~30 s once). Runs, each a fresh fit of `--seconds` of training (FitConfig.time_budget_s; no validation, one
checkpoint at the end), the global batch as the preset says (cpu-mlp: 512 rays over 4 images):

- N = 1 with 1 thread, N = 1 with `--threads` threads (the whole CPU for one process),
- N = 2, ranks of 1 thread each (`--nproc 2`, gloo), the same global batch (each rank: half the rays).

Parts (`--parts`, default all):
- `wall`: steps/s = steps / training seconds (set-up excluded); rays/s = steps x rays_per_batch / training seconds
  (all ranks together). On a shared machine these move with the other load: compare runs taken together.
- `cpu`: CPU seconds per step of all ranks together: fits of 3 and of 3 + `--cpu-steps` steps, the difference of
  their CPU time (this process, or the waited-for children's rusage) over the difference of steps.
- `phases`: CPU seconds per step of rank 0 in the forward pass (`Replicas.forward`), the backward pass and the
  synchronisation (`Replicas.sync`), wrapped with `time.process_time`: 1 process at the full and at half the batch,
  and rank 0 of 2 ranks. The least load-sensitive figure: on an idle machine with a core per rank the wall time per
  step is about rank 0's CPU time per step.
- `sync`: the median time of one gloo all-reduce of a flat float32 buffer the size of the model's gradients (+ one
  MAX all-reduce of the occupancy grids), 2 ranks.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path

from avatarctl.lists import split_list


def ensure_project(cache: Path) -> Path:
    """A tiny synthetic project in `cache` (made once)."""
    from avatarctl.stages import ingest, synth
    from avatarctl.stages.ingest import IngestConfig
    from avatarctl.synth.config import SynthConfig

    proj = cache / "proj"
    if (proj / "project.json").is_file():
        return proj
    shutil.rmtree(cache, ignore_errors=True)
    cache.mkdir(parents=True)
    synth.run(cache / "cap", SynthConfig.preset("tiny"))
    ingest.run(proj, IngestConfig(capture=cache / "cap", project=proj))
    return proj


def fit_once(project: Path, work: Path, nproc: int, threads: int, seconds: float, preset: str) -> dict:
    import torch

    from avatarctl.stages import fit
    from avatarctl.stages.fit import FitRequest

    dest = work / f"n{nproc}_t{threads}"
    shutil.rmtree(dest, ignore_errors=True)
    shutil.copytree(project, dest, ignore=shutil.ignore_patterns("fit", "render", "eval"))
    os.environ["OMP_NUM_THREADS"] = str(threads)  # the spawned ranks read it when they import torch
    torch.set_num_threads(threads)
    req = FitRequest(preset=preset, iters=1_000_000, device="cpu", nproc=nproc,
                     settings={"time_budget_s": float(seconds), "val_every": 0, "val_pairs": 0, "log_every": 10,
                               "checkpoint_every": 1000000})
    res = fit.run(dest, req, handle_sigint=False)
    steps = res.step
    return {"nproc": nproc, "threads_per_rank": threads, "steps": steps, "train_seconds": round(res.seconds, 2),
            "setup_seconds": round(res.setup_seconds, 2), "steps_per_s": round(steps / res.seconds, 3),
            "rays_per_s": round(steps * res.config.rays_per_batch / res.seconds, 1),
            "rays_per_batch": res.config.rays_per_batch, "final_mse": res.losses.get("mse")}


def cpu_per_step(project: Path, work: Path, nproc: int, steps: int, preset: str) -> float:
    """CPU seconds per training step of all ranks together (1 thread each), set-up cancelled out."""
    import resource
    import time

    import torch

    from avatarctl.stages import fit
    from avatarctl.stages.fit import FitRequest

    os.environ["OMP_NUM_THREADS"] = "1"
    torch.set_num_threads(1)
    used = []
    for iters in (3, 3 + steps):
        dest = work / f"cpu_n{nproc}_{iters}"
        shutil.rmtree(dest, ignore_errors=True)
        shutil.copytree(project, dest, ignore=shutil.ignore_patterns("fit", "render", "eval"))
        r0, c0 = resource.getrusage(resource.RUSAGE_CHILDREN), time.process_time()
        fit.run(dest, FitRequest(preset=preset, iters=iters, device="cpu", nproc=nproc,
                                 settings={"val_every": 0, "val_pairs": 0, "log_every": 10}), handle_sigint=False)
        r1, c1 = resource.getrusage(resource.RUSAGE_CHILDREN), time.process_time()
        used.append((c1 - c0) if nproc == 1 else (r1.ru_utime + r1.ru_stime - r0.ru_utime - r0.ru_stime))
    return (used[1] - used[0]) / steps


@contextmanager
def _timed() -> Iterator[dict[str, float]]:
    """Wrap Replicas.forward / Replicas.sync / Tensor.backward of this process with CPU-time accumulators while the
    block runs (put back after it: `main` may run inside another program, the tests)."""
    import time

    import torch

    from avatarctl.fit import distributed

    acc = {"forward": 0.0, "backward": 0.0, "sync": 0.0, "steps": 0.0}
    saved = []

    def wrap(owner: object, name: str, key: str) -> None:
        inner = getattr(owner, name)
        saved.append((owner, name, inner))

        def timed(*a, **k):
            t = time.process_time()
            out = inner(*a, **k)
            acc[key] += time.process_time() - t
            acc["steps"] += key == "forward"
            return out

        setattr(owner, name, timed)

    try:
        wrap(distributed.Replicas, "forward", "forward")
        wrap(distributed.Replicas, "sync", "sync")
        wrap(torch.Tensor, "backward", "backward")
        yield acc
    finally:
        for owner, name, inner in reversed(saved):
            setattr(owner, name, inner)


def _phases_rank(env, channel, project: str, req) -> dict[str, float]:
    from avatarctl.stages.fit import _fit_rank

    with _timed() as acc:
        _fit_rank(env, channel, project, req)
    return dict(acc)


def phase_times(project: Path, work: Path, nproc: int, rays: int, images: int, steps: int, preset: str) -> dict:
    """CPU seconds per step by phase (rank 0), 1 thread per rank."""
    import torch

    from avatarctl.dist import launch
    from avatarctl.stages import fit
    from avatarctl.stages.fit import FitRequest

    dest = work / f"phases_n{nproc}_{rays}"
    shutil.rmtree(dest, ignore_errors=True)
    shutil.copytree(project, dest, ignore=shutil.ignore_patterns("fit", "render", "eval"))
    os.environ["OMP_NUM_THREADS"] = "1"
    req = FitRequest(preset=preset, iters=steps, device="cpu", nproc=nproc,
                     overrides=("val_every=0", "val_pairs=0", "log_every=10", f"rays_per_batch={rays}",
                                f"images_per_batch={images}"))
    if nproc == 1:
        torch.set_num_threads(1)
        with _timed() as acc:
            fit.run(dest, req, handle_sigint=False)
    else:
        acc = launch(_phases_rank, nproc, (str(dest), req), what="phase benchmark")
    n = max(acc["steps"], 1.0)
    return {"nproc": nproc, "rays_per_batch": rays,
            **{f"{k}_cpu_s": round(v / n, 4) for k, v in acc.items() if k != "steps"}}


def _allreduce_rank(env, channel, numel: int, occ: int, reps: int) -> float:
    """One rank of the all-reduce timing: median seconds of SUM(numel) + MAX(occ), as `Replicas.sync` does."""
    import statistics
    import time

    import torch
    import torch.distributed as dist

    from avatarctl.dist import process_group

    with process_group(env, torch.device("cpu")):
        flat, grid = torch.ones(numel), torch.ones(occ)
        times = []
        for _ in range(reps + 2):
            dist.barrier()
            t0 = time.perf_counter()
            dist.all_reduce(flat)
            if occ:
                dist.all_reduce(grid, op=dist.ReduceOp.MAX)
            times.append(time.perf_counter() - t0)
        return statistics.median(times[2:])


def allreduce_seconds(numel: int, occ: int, reps: int = 10) -> float:
    from avatarctl.dist import launch

    os.environ["OMP_NUM_THREADS"] = "1"
    return launch(_allreduce_rank, 2, (numel, occ, reps), what="all-reduce benchmark")


def model_sizes(project: Path, preset: str) -> tuple[int, int]:
    """(parameters, occupancy cells) of the preset's model on the project's body."""
    from avatarctl.body.registry import load_body_model
    from avatarctl.fit.config import resolve_fit_config
    from avatarctl.fit.loop import decide_auto
    from avatarctl.io.project_io import load_project_capture
    from avatarctl.model.avatar import SlrfAvatar
    from avatarctl.project import Project

    proj = Project.open(project)
    cfg = decide_auto(resolve_fit_config(preset), proj)  # pose refinement 'auto' decided as the fit decides it
    cap = load_project_capture(proj)
    body = load_body_model(cap.body_model, cap.body_model_path)
    model = SlrfAvatar(cfg.model, body.template(cap.motion), num_frames=len(cap.split.train_frames))
    occ = model.occupancy.numel() if model.cfg.uses_occupancy else 0
    return sum(p.numel() for p in model.parameters()), occ


PARTS = ("wall", "cpu", "phases", "sync")


@dataclass(frozen=True)
class DistBench:
    """What `main` measured (also written to `--out`); a part not run is empty."""
    project: str
    preset: str
    seconds: float
    ranks: tuple[int, ...]  # the rank counts measured
    runs: tuple[dict, ...]  # `wall`: one row per (ranks, threads per rank) fit, as `fit_once` returns it
    cpu_time: dict[str, float]  # `cpu`: n<ranks>_cpu_s_per_step
    phases: tuple[dict, ...]  # `phases`: CPU seconds per step of rank 0 by phase
    sync: dict[str, float]  # `sync`: parameters, occupancy cells, all-reduce seconds (2 ranks)


def main(argv: list[str] | None = None) -> DistBench:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--project", type=Path, default=None)
    ap.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "avatarctl_bench_dist")
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--threads", type=int, default=2, help="threads of the one-process comparison run")
    ap.add_argument("--preset", default="cpu-mlp", help="cpu-mlp (the MLP fields: the cpu preset of the figures in "
                                                        "docs/distributed.md) or cpu (the Gaussian fields)")
    ap.add_argument("--out", type=Path, default=Path("bench_dist.json"))
    ap.add_argument("--parts", default=",".join(PARTS), help="which measurements: wall, cpu, phases, sync (comma list)")
    ap.add_argument("--ranks", default="1,2", help="rank counts to measure: 1, 2 (comma list; sync needs 2)")
    ap.add_argument("--cpu-steps", type=int, default=20, help="steps of the CPU-time runs")
    args = ap.parse_args(argv)
    parts = set(split_list(args.parts))
    ranks = tuple(sorted(set(split_list(args.ranks, int))))
    if not parts <= set(PARTS):
        ap.error(f"unknown --parts {sorted(parts - set(PARTS))}: use {', '.join(PARTS)}")
    if not ranks or not set(ranks) <= {1, 2}:
        ap.error(f"--ranks {args.ranks!r}: use 1, 2 or 1,2")
    project = args.project or ensure_project(args.cache)
    work = args.cache / "runs"
    work.mkdir(parents=True, exist_ok=True)
    rows = []
    wall = (list(dict.fromkeys([(1, 1), (1, args.threads)])) if 1 in ranks else []) + ([(2, 1)] if 2 in ranks else [])
    for nproc, threads in wall if "wall" in parts else ():
        row = fit_once(project, work, nproc, threads, args.seconds, args.preset)
        print(json.dumps(row), flush=True)
        rows.append(row)
    cpu = {}
    for nproc in ranks if "cpu" in parts else ():
        cpu[f"n{nproc}_cpu_s_per_step"] = round(cpu_per_step(project, work, nproc, args.cpu_steps, args.preset), 3)
        print(json.dumps(cpu), flush=True)
    phases = []
    if "phases" in parts:
        from avatarctl.fit.config import preset as fit_preset

        full = fit_preset(args.preset)
        r, b = full.rays_per_batch, full.images_per_batch
        runs = ([(1, r, b), (1, r // 2, b // 2)] if 1 in ranks else []) + ([(2, r, b)] if 2 in ranks else [])
        for nproc, rays, images in runs:
            phases.append(phase_times(project, work, nproc, rays, images, args.cpu_steps, args.preset))
            print(json.dumps(phases[-1]), flush=True)
    sync = {}
    if "sync" in parts and 2 in ranks:
        params, occ = model_sizes(project, args.preset)
        sync = {"parameters": params, "occupancy_cells": occ, "allreduce_s": round(allreduce_seconds(params, occ), 4)}
        print(json.dumps(sync), flush=True)
    elif "sync" in parts:
        print("sync: the all-reduce needs 2 ranks (--ranks 1): not measured", flush=True)
    res = DistBench(project=str(project), preset=args.preset, seconds=args.seconds, ranks=ranks, runs=tuple(rows),
                    cpu_time=cpu, phases=tuple(phases), sync=sync)
    args.out.write_text(json.dumps({"cpu_count": os.cpu_count(), **asdict(res)}, indent=2))
    print(f"wrote {args.out}")
    return res


if __name__ == "__main__":
    main()
