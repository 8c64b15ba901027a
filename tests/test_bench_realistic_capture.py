"""benchmarks/realistic_capture.py at toy scale: the captures a config makes (clean twin, realistic, one per
imperfection), and the whole run on micro captures cut to 3 + 2 frames (synth, ingest, a 1 s fit, eval; with the
colour transform on as a second row each): the table, JSON and eval sheets written."""

from __future__ import annotations

import csv
import json
import math

import pytest


def test_captures_are_the_clean_twin_the_realistic_one_and_one_per_imperfection():
    from avatarctl.synth import SynthConfig
    from benchmarks.realistic_capture import captures, ingest_options

    config = SynthConfig.preset("realistic", seed=1)
    caps = {c.name: c.config for c in captures(config)}
    assert list(caps) == ["clean", "realistic", "colour", "noise", "jpeg", "blur", "masks", "fits"]
    assert caps["clean"].imperfections == {} and caps["realistic"] == config
    assert set(caps["colour"].imperfections) == {"exposure_ev", "white_balance", "held_out_ev"}
    for name in ("noise", "jpeg", "blur", "masks", "fits"):
        assert len(caps[name].imperfections) == 1, name
        assert all(caps[name].seed == 1 and caps[name].size == config.size for name in caps)
    assert ingest_options(caps["masks"]) == {"masks": "mediapipe", "fits": "files"}
    assert ingest_options(caps["fits"]) == {"masks": "files", "fits": "keypoints"}
    assert [c.name for c in captures(config, ["clean", "blur"])] == ["clean", "blur"]
    with pytest.raises(SystemExit, match="fit_noise"):
        captures(config, ["fit_noise"])  # the realistic preset has no fit noise (its fits are estimated)


@pytest.mark.anny
def test_the_benchmark_runs_at_toy_scale(tmp_path):
    from benchmarks.realistic_capture import main

    out = tmp_path / "bench"
    small = ["--synth-set", "train_frames=3", "--synth-set", "test_frames=2", "--synth-set", "garment=none",
             "--synth-set", "exposure_ev=0.4", "--synth-set", "noise_std=0.02"]
    res = main([str(out), "--preset", "micro", "--seed", "2", *small, "--only", "clean,colour", "--colour",
                "--budget-s", "1", "--fit-preset", "micro", "--set", "log_every=1"])
    assert [r["name"] for r in res.rows] == ["clean", "clean+colour", "colour", "colour+colour"]
    for r in res.rows:
        assert math.isfinite(r["psnr"]) and r["fit_steps"] > 0 and r["images"] > 0
        assert r["matched_psnr"] is not None and (out / "sheets" / f"{r['name']}.png").is_file()
    clean, colour = res.rows[0], res.rows[2]
    assert clean["cost_db"] == 0.0 and math.isclose(colour["cost_db"], clean["psnr"] - colour["psnr"], abs_tol=1e-3)
    assert json.loads(colour["imperfections"]) == {"exposure_ev": 0.4}
    with res.csv.open() as fh:
        table = list(csv.DictReader(fh))
    assert [t["name"] for t in table] == [r["name"] for r in res.rows]
    meta = json.loads(res.json.read_text())
    assert "NeRF-W" in meta["protocol"] and meta["synth"]["colour"]["exposure_ev"] == 0.4
    assert meta["synth"]["clean"]["exposure_ev"] == 0.0 and meta["budget_s"] == 1.0
    # the clean twin's cameras have gain 1: its images in its own units are its plain figure
    assert math.isclose(clean["clean_units_psnr"], clean["psnr"], abs_tol=0.05)
    assert colour["clean_units_psnr"] is not None and colour["units_cost_db"] is not None


def test_clean_units_psnr_takes_a_brighter_camera_back_to_the_clean_exposure():
    """An avatar as good as the clean twin's, seen by a camera g times brighter per channel (render and photograph
    alike), scores lower by the brightness alone; in the clean twin's units it scores what the clean twin did."""
    import numpy as np

    from avatarctl.evaluate.metrics import mse, mse_channels, psnr
    from avatarctl.evaluate.report import ImageScore
    from benchmarks.realistic_capture import clean_units_psnr

    def score(channels):  # the fields clean_units_psnr reads; the rest as an eval would fill them
        return ImageScore(frame=0, view="cam01", psnr=0.0, ssim=0.0, mse=0.0, pixels=1, latent="mean", seconds=0.0,
                          mse_rgb=channels)

    rng = np.random.default_rng(0)
    truth = rng.uniform(0.1, 0.6, (2, 16, 16, 3))
    render = np.clip(truth + rng.normal(0, 0.05, truth.shape), 0, 1)
    g = np.array([1.4, 1.3, 1.2])
    rows = []
    for k in range(2):
        channels = mse_channels(render[k] * g, truth[k] * g)
        assert math.isclose(channels.mean(), mse(render[k] * g, truth[k] * g), rel_tol=1e-6)
        rows.append(score(tuple(float(c) for c in channels)))
    clean = float(np.mean([psnr(render[k], truth[k]) for k in range(2)]))
    bright = float(np.mean([psnr(render[k] * g, truth[k] * g) for k in range(2)]))
    assert bright < clean - 2.0  # the brightness alone costs 20 log10(~1.3) dB
    assert math.isclose(clean_units_psnr(rows, {"cam01": list(g)}), clean, abs_tol=1e-4)  # float32 images
    assert math.isclose(clean_units_psnr(rows, {}), bright, abs_tol=1e-4)  # a view without a gain: as recorded
    assert clean_units_psnr([score(None)], {}) is None


@pytest.mark.anny
def test_true_masks_project_scores_against_the_true_silhouette_where_ingest_estimated_it(tmp_path):
    """A project whose masks ingest estimated (here from background plates) gets, in a copy, its held-out views'
    true masks exactly as ingest writes a capture's mask files (the same undistortion); its training views and the
    original project are untouched; a project ingested from the true masks gets no copy."""
    import shutil

    import numpy as np

    from avatarctl.io.project_io import read_mask
    from avatarctl.project import Project
    from avatarctl.stages import ingest, synth
    from avatarctl.stages.ingest import IngestConfig
    from avatarctl.synth import SynthConfig
    from benchmarks.realistic_capture import true_masks_project

    cfg = SynthConfig.preset("micro", 2, train_frames=2, test_frames=1, garment="none", masks="none")
    cap, proj = tmp_path / "cap", tmp_path / "proj"
    synth.run(cap, cfg)
    ingest.run(proj, IngestConfig(capture=cap, project=proj, masks="background", contact_sheet=False))
    # the same capture with its true masks where ingest reads mask files: what ingest makes of the truth
    cap2, proj2 = tmp_path / "cap2", tmp_path / "proj2"
    shutil.copytree(cap, cap2)
    shutil.move(cap2 / "gt" / "masks", cap2 / "masks")
    meta = json.loads((cap2 / "capture.json").read_text())
    meta["config"]["masks"] = "truth"
    (cap2 / "capture.json").write_text(json.dumps(meta))
    ingest.run(proj2, IngestConfig(capture=cap2, project=proj2, contact_sheet=False))

    before = {p: p.read_bytes() for p in (proj / "ingest" / "masks").rglob("*.png")}
    copy = true_masks_project(proj, cap, tmp_path / "copy")
    assert copy is not None and {p: p.read_bytes() for p in (proj / "ingest" / "masks").rglob("*.png")} == before
    split = json.loads((proj / "ingest" / "split.json").read_text())
    P, C, T = Project.open(proj), Project.open(copy), Project.open(proj2)
    frames = sorted(int(p.stem) for p in (proj / "ingest" / "masks" / split["test_views"][0]).glob("*.png"))
    assert frames
    changed = 0
    for v in split["test_views"]:
        for f in frames:
            assert np.array_equal(read_mask(C, v, f), read_mask(T, v, f))
            changed += int(not np.array_equal(read_mask(C, v, f), read_mask(P, v, f)))
    for v in split["train_views"]:
        for f in frames:
            assert np.array_equal(read_mask(C, v, f), read_mask(P, v, f))
    assert changed > 0  # the plates' masks are not the truth on every frame
    assert true_masks_project(proj2, cap2, tmp_path / "copy2") is None
