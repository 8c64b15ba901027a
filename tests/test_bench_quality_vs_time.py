"""benchmarks/quality_vs_time.py at toy scale: one backend, a snapshot after 0.6 s of a micro fit on the toy
project, its eval, a 48 px render timing; the table, JSON and plot written (three `avatarctl` subprocesses)."""

from __future__ import annotations

import csv
import json
import math


def test_quality_vs_time_fits_scores_and_tabulates_a_toy_backend(toy_fitted_project, tmp_path):
    from benchmarks.quality_vs_time import main

    out = tmp_path / "qvt"
    res = main([str(toy_fitted_project), str(out), "--backend", "mlp=log_every=1", "--minutes", "0.01", "--preset", "micro",
                "--parallel", "1", "--every", "1", "--render-size", "48", "--render-threads", "1"])
    (row,) = res.rows
    assert row["backend"] == "mlp" and row["overrides"] == "log_every=1"  # a loaded machine may run < 10 steps
    assert row["minutes"] == 0.01 and row["images"] > 0
    assert math.isfinite(row["psnr_bbox"]) and row["psnr_bbox"] > 0 and 0 < row["ssim_bbox"] <= 1
    assert row["steps"] > 0 and row["steps_per_s"] > 0 and row["rays_per_s"] > 0
    assert row["render_48_size"] == [48, 48] and row["render_48_s"] > 0 and row["render_native_size"] == [32, 32]
    with res.csv.open() as f:
        table = list(csv.DictReader(f))
    assert len(table) == 1 and float(table[0]["psnr_bbox"]) == row["psnr_bbox"]
    meta = json.loads(res.json.read_text())
    assert "bbox protocol" in meta["protocol"] and meta["rows"][0]["steps"] == row["steps"]
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        assert res.plot is None
    else:
        assert res.plot.is_file() and res.plot.stat().st_size > 0


def test_the_plot_has_a_panel_per_region_with_its_flat_colour(tmp_path):
    """`--region garment` rows (garment and body PSNR, each with its flat-colour PSNR) -> the bbox panel and one panel
    per region, in the rows' order; without regions, the bbox panel alone."""
    import pytest

    from benchmarks.quality_vs_time import _plot, _region_names

    rows = [{"backend": b, "minutes": m, "psnr_bbox": 21 + m / 10 + i, "garment_psnr": 15.6 + m / 20,
             "body_psnr": 29 + m / 5, "garment_flat_colour_psnr": 15.5, "body_flat_colour_psnr": 20.2}
            for i, b in enumerate(("gaussians", "mlp")) for m in (2, 5)]
    assert _region_names(rows) == ["garment", "body"]
    assert _region_names([{"backend": "a", "minutes": 1, "psnr_bbox": 20.0}]) == []
    pytest.importorskip("matplotlib")
    from PIL import Image

    wide, narrow = _plot(rows, tmp_path / "r.png", "protocol"), _plot(
        [{k: v for k, v in r.items() if not k.startswith(("garment", "body"))} for r in rows], tmp_path / "b.png", "p")
    assert Image.open(wide).width > 2 * Image.open(narrow).width  # three panels against one
