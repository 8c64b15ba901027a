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
