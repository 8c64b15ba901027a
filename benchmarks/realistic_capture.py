"""What each imperfection of a real capture costs, and the gap between a realistic synth capture and its clean twin
(issue 51; not a test).

For a synth preset and seed (default `realistic`: 4 cameras, every imperfection), the script builds the clean twin
(`SynthConfig.clean_twin`: same seed, same scene), the realistic capture, and one capture per single imperfection
(`colour`: exposure + white balance + the held-out cameras' offset; `noise`; `jpeg`; `blur`; `masks`: MediaPipe masks; `fits`: keypoint-fitted
anny, or `fit_noise`: fits with --fit-noise errors), ingests each (`--masks mediapipe` / `--fits keypoints` where the
capture leaves them out), fits each for the same wall-time budget (`--set time_budget_s=...`), evaluates the held-out
views of the training frames (bbox protocol; the plain PSNR and NeRF-W's colour-matched one, `avatarctl eval`), and
writes the table: per capture its PSNR / SSIM, the colour-matched PSNR, and the cost against the clean twin; and the
same images in the clean twin's units (`clean_units_psnr`): a camera g times brighter records the avatar's error
g times larger too, so a capture whose held-out camera is brighter than the clean twin's loses 20 log10 g dB however
good its avatar; each image's error is divided per channel by its camera's true gain (capture.json "camera_colour";
the eval's per-channel MSE), and `units_cost_db` is the cost left against the clean twin. A capture whose masks
ingest estimated is scored against the held-out views' estimated masks (what a user's eval does); `true_masks_psnr`
(and `true_masks_units_psnr`, in the clean twin's units) scores the same avatar against the held-out views' true
masks (the synth capture's, undistorted as ingest does: `true_masks_project`), so the gap splits into the avatar's
and the estimated ground truth's. With
`--colour` every capture is also fitted with the per-camera colour transforms on (`model.colour.enabled=true`,
rows `<name>+colour`): the lever measured against the capture it is meant for.

    python -m benchmarks.realistic_capture OUT [--preset realistic] [--seed 0] [--budget-s 600] [--fit-preset cpu]
        [--only clean,realistic,colour] [--colour] [--set KEY=VALUE ...] [--synth-set FIELD=VALUE ...]
        [--every 1] [--device cpu]

`--synth-set` overrides fields of the synth config for every capture (the toy test: `train_frames=3`). Each step
writes into OUT/<name>/ (capture/, project/), so a second run with the same OUT reuses what exists (`--reuse`).
Writes OUT/results.csv, OUT/results.json (the command line, the configs, the protocol) and OUT/sheets/<name>.png
(each eval's comparison sheet). MediaPipe (the `capture` extra) is needed for the `masks` and `fits` captures.
"""

from __future__ import annotations

import argparse
import csv
import json
import resource
import shutil
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

# a single imperfection -> the SynthConfig fields that make it (taken from the realistic config)
SINGLES: dict[str, tuple[str, ...]] = {
    "colour": ("exposure_ev", "white_balance", "held_out_ev"), "noise": ("noise_std",), "jpeg": ("jpeg_quality",),
    "blur": ("shutter_s",), "masks": ("masks",), "fits": ("fits",),
    "fit_noise": ("fit_noise_deg", "fit_noise_cm", "fit_noise_corr_frames"),
}
PROTOCOL = ("novel_view split (training frames, held-out views), bbox protocol; psnr: plain; matched_psnr: NeRF-W's "
            "colour-matched PSNR (colour fitted on the left half, scored on the right half; matched_plain_psnr: the "
            "plain render on the same right halves); cost_db: clean twin's psnr minus this capture's; "
            "clean_units_psnr: the same images with each channel's error divided by the camera's true gain "
            "(capture.json camera_colour), mean over images; units_cost_db: the clean twin's psnr minus it; "
            "true_masks_psnr / true_masks_units_psnr: the same avatar and images with the held-out views' true masks "
            "(captures whose masks ingest estimated); true_masks_units_cost_db: the clean twin's psnr minus the latter")


@dataclass(frozen=True)
class Capture:
    """One capture of the comparison: its name and synth config."""

    name: str
    config: Any  # SynthConfig


def captures(config: Any, only: list[str] | None = None) -> list[Capture]:
    """The clean twin, the realistic capture and one capture per imperfection `config` has (in `SINGLES` order),
    optionally restricted to the names in `only`."""
    clean = config.clean_twin()
    out = [Capture("clean", clean), Capture("realistic", config)]
    have = config.imperfections
    for name, keys in SINGLES.items():
        if any(k in have for k in keys):
            out.append(Capture(name, replace(clean, **{k: getattr(config, k) for k in keys})))
    if only:
        unknown = sorted(set(only) - {c.name for c in out})
        if unknown:
            raise SystemExit(f"--only: {unknown} are not captures of this config (have {[c.name for c in out]})")
        out = [c for c in out if c.name in only]
    return out


def ingest_options(config: Any) -> dict[str, str]:
    """What ingest must estimate for a capture: MediaPipe masks / keypoint fits where the capture leaves them out."""
    return {"masks": "mediapipe" if config.masks == "none" else "files",
            "fits": "keypoints" if config.fits == "none" else "files"}


def clean_units_psnr(scores: list[Any], gains: dict[str, list[float]]) -> float | None:
    """The mean over images (`scores`: an eval's `evaluate.report.ImageScore`s) of the PSNR with each channel's
    squared error divided by the square of its camera's true gain (`gains`: view -> [3], a synth capture's
    capture.json "camera_colour"; 1 for a view without one): the error as a camera with the clean twin's exposure
    would record it. None without per-channel errors."""
    import numpy as np

    from avatarctl.evaluate.metrics import psnr_from_mse

    if not scores or any(s.mse_rgb is None for s in scores):
        return None
    out = []
    for s in scores:
        g = np.asarray(gains.get(s.view, (1.0, 1.0, 1.0)), dtype=np.float64)
        out.append(psnr_from_mse(float(np.mean(np.asarray(s.mse_rgb) / g ** 2))))
    return float(np.mean(out))


def true_masks_project(project: Path, capture: Path, out: Path) -> Path | None:
    """A copy at `out` of the fitted `project` (its ingest and fit; no eval) whose held-out views' masks are the synth
    `capture`'s true ones (gt/masks, or masks/ where synth left the truth there), undistorted and resized as ingest
    does (`Undistorter.mask`): an eval there scores the avatar against the true silhouette. None when the project's
    masks are the capture's files already (nothing to replace) or the capture holds no true masks."""
    import cv2

    from avatarctl.ingest.readers import read_easymocap
    from avatarctl.ingest.undistort import Undistorter
    from avatarctl.io.gt_geometry import masks_are_ground_truth
    from avatarctl.io.project_io import load_split, write_mask
    from avatarctl.project import Project
    from avatarctl.synth.capture import GT_MASKS

    ingest = Project.open(project).require("ingest")
    truth = next((d for d in (capture / GT_MASKS, capture / "masks") if d.is_dir()), None)
    if truth is None or masks_are_ground_truth(capture, ingest.config.get("resolved", {}).get("masks")):
        return None
    if out.exists():
        shutil.rmtree(out)
    shutil.copytree(project, out, ignore=shutil.ignore_patterns("eval"))
    copy = Project.open(out)
    cams = {c.name: c for c in read_easymocap(capture).cameras}
    for v in load_split(copy.paths.split).test_views:
        und = Undistorter.for_camera(cams[v], float(ingest.config.get("resize", 1.0)))
        for path in sorted((truth / v).glob("*.png")):
            if copy.paths.mask(v, int(path.stem)).is_file():
                write_mask(copy, v, int(path.stem), und.mask(cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) > 127))
    return out


def _peak_rss_gb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20


def _build(cap: Capture, root: Path, reuse: bool, log) -> tuple[Path, dict[str, float]]:
    """Synthesize and ingest one capture into root/<name>/ -> (project, seconds per step)."""
    from avatarctl.stages import ingest, synth
    from avatarctl.stages.ingest import IngestConfig

    folder = root / cap.name
    capture, project = folder / "capture", folder / "project"
    seconds: dict[str, float] = {}
    if not (reuse and (capture / "capture.json").is_file()):
        shutil.rmtree(capture, ignore_errors=True)
        t = time.perf_counter()
        synth.run(capture, cap.config)
        seconds["synth_s"] = round(time.perf_counter() - t, 2)
        log(f"{cap.name}: synth {seconds['synth_s']} s")
    if not (reuse and (project / "ingest" / "split.json").is_file()):
        shutil.rmtree(project, ignore_errors=True)
        t = time.perf_counter()
        ingest.run(project, IngestConfig(capture=capture, project=project, contact_sheet=False,
                                         **ingest_options(cap.config)))
        seconds["ingest_s"] = round(time.perf_counter() - t, 2)
        log(f"{cap.name}: ingest {seconds['ingest_s']} s ({ingest_options(cap.config)})")
    return project, seconds


def _fit_and_eval(name: str, project: Path, fit_preset: str, budget_s: float, sets: list[str], every: int,
                  device: str, sheets: Path, log) -> dict[str, Any]:
    from avatarctl.stages import evaluate, fit
    from avatarctl.stages.evaluate import EvalConfig
    from avatarctl.stages.fit import FitRequest

    t = time.perf_counter()
    fr = fit.run(project, FitRequest(preset=fit_preset, iters=10**9, overrides=tuple(sets), fresh=True,
                                     settings={"time_budget_s": float(budget_s)}, device=device),
                 handle_sigint=False)
    fit_wall = time.perf_counter() - t
    er = evaluate.run(project, EvalConfig(split="novel_view", name="bench_" + name.replace("+", "_"), every=every,
                                          device=device))
    m = er.metrics
    if (er.out_dir / "sheet.png").is_file():
        shutil.copyfile(er.out_dir / "sheet.png", sheets / f"{name}.png")
    cm = m.colour_matched
    gains = json.loads((project.parent / "capture" / "capture.json").read_text()).get("camera_colour", {})
    units = clean_units_psnr(er.scores, gains)
    true_psnr = true_units = None
    copy = true_masks_project(project, project.parent / "capture", project.parent / "true_masks_project")
    if copy is not None:
        tr = evaluate.run(copy, EvalConfig(split="novel_view", name="bench_true_masks", every=every, device=device))
        true_psnr, true_units = tr.metrics.psnr, clean_units_psnr(tr.scores, gains)
        if (tr.out_dir / "sheet.png").is_file():
            shutil.copyfile(tr.out_dir / "sheet.png", sheets / f"{name}_true_masks.png")
        shutil.rmtree(copy)
    row = {"name": name, "psnr": round(m.psnr, 4), "ssim": round(m.ssim, 5),
           "clean_units_psnr": round(units, 4) if units is not None else None,
           "true_masks_psnr": round(true_psnr, 4) if true_psnr is not None else None,
           "true_masks_units_psnr": round(true_units, 4) if true_units is not None else None,
           "matched_psnr": round(cm["psnr"], 4) if cm else None,
           "matched_plain_psnr": round(cm["plain_psnr"], 4) if cm else None,
           "matched_gain": json.dumps(cm["gain"]) if cm else None, "images": m.images,
           "fit_steps": fr.step, "fit_seconds": round(fr.seconds, 1), "fit_wall_s": round(fit_wall, 1),
           "eval_s": round(er.seconds, 1), "peak_rss_gb": round(_peak_rss_gb(), 2)}
    log(f"{name}: {fr.step} steps in {fr.seconds:.0f} s -> PSNR {m.psnr:.2f} dB, matched "
        f"{row['matched_psnr']} (plain on the same halves {row['matched_plain_psnr']})")
    return row


@dataclass(frozen=True)
class Result:
    rows: list[dict[str, Any]]
    csv: Path
    json: Path


def main(argv: list[str] | None = None) -> Result:
    from avatarctl.synth.config import SynthConfig

    ap = argparse.ArgumentParser(prog="python -m benchmarks.realistic_capture", description=__doc__.split("\n")[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--preset", default="realistic", help="synth preset (its imperfections are the realistic ones)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--synth-set", action="append", default=[], metavar="FIELD=VALUE",
                    help="override a SynthConfig field for every capture (ints, floats or words)")
    ap.add_argument("--budget-s", type=float, default=600.0, help="fit wall-time budget per capture (seconds)")
    ap.add_argument("--fit-preset", default="cpu")
    ap.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE",
                    help="a fit --set override for every fit")
    ap.add_argument("--only", default="", help="comma list of captures (clean, realistic, colour, noise, jpeg, blur, "
                                               "masks, fits, fit_noise); default: all the config has")
    ap.add_argument("--colour", action="store_true", help="also fit each capture with model.colour.enabled=true")
    ap.add_argument("--every", type=int, default=1, help="eval every N-th frame")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--reuse", action="store_true", help="keep captures and projects already in OUT")
    a = ap.parse_args(argv)

    overrides = {}
    for item in a.synth_set:
        key, _, text = item.partition("=")
        value: Any = text
        for conv in (int, float):
            try:
                value = conv(text)
                break
            except ValueError:
                continue
        overrides[key.strip()] = value
    config = SynthConfig.preset(a.preset, a.seed, **overrides)
    todo = captures(config, [s for s in a.only.split(",") if s.strip()] or None)
    out = a.out
    sheets = out / "sheets"
    sheets.mkdir(parents=True, exist_ok=True)

    def log(msg: str) -> None:
        print(msg, flush=True)

    rows: list[dict[str, Any]] = []
    for cap in todo:
        project, seconds = _build(cap, out, a.reuse, log)
        variants = [(cap.name, list(a.sets))]
        if a.colour:
            variants.append((f"{cap.name}+colour", list(a.sets) + ["model.colour.enabled=true"]))
        for name, sets in variants:
            row = _fit_and_eval(name, project, a.fit_preset, a.budget_s, sets, a.every, a.device, sheets, log)
            rows.append({**row, "capture": cap.name, "imperfections": json.dumps(cap.config.imperfections),
                         "colour_transform": name.endswith("+colour"), **seconds})
    clean = {r["colour_transform"]: r["psnr"] for r in rows if r["capture"] == "clean"}
    for r in rows:
        base = clean.get(r["colour_transform"])
        r["cost_db"] = round(base - r["psnr"], 4) if base is not None else None
        u = r["clean_units_psnr"]
        r["units_cost_db"] = round(base - u, 4) if base is not None and u is not None else None
        t = r["true_masks_units_psnr"]
        r["true_masks_units_cost_db"] = round(base - t, 4) if base is not None and t is not None else None
    keys = ["name", "capture", "colour_transform", "imperfections", "psnr", "ssim", "matched_psnr",
            "matched_plain_psnr", "cost_db", "clean_units_psnr", "units_cost_db", "true_masks_psnr",
            "true_masks_units_psnr", "true_masks_units_cost_db", "matched_gain", "images",
            "fit_steps", "fit_seconds", "fit_wall_s",
            "eval_s", "synth_s", "ingest_s", "peak_rss_gb"]
    csv_path, json_path = out / "results.csv", out / "results.json"
    with csv_path.open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=keys, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
    json_path.write_text(json.dumps({"command": [sys.argv[0]] + list(argv if argv is not None else sys.argv[1:]),
                                     "protocol": PROTOCOL, "budget_s": a.budget_s, "fit_preset": a.fit_preset,
                                     "sets": a.sets, "synth": {c.name: c.config.to_json() for c in todo},
                                     "rows": rows}, indent=2) + "\n")
    for r in rows:
        log(f"{r['name']:<22} PSNR {r['psnr']:7.3f}  cost {r['cost_db'] if r['cost_db'] is not None else '-':>8}  "
            f"clean units {r['clean_units_psnr']} (cost {r['units_cost_db']})  "
            f"true masks {r['true_masks_psnr']} / units {r['true_masks_units_psnr']}  "
            f"matched {r['matched_psnr']}  steps {r['fit_steps']}")
    return Result(rows=rows, csv=csv_path, json=json_path)


if __name__ == "__main__":
    main()
