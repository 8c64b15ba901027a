"""benchmarks/viewer_frame_time.py on the fitted toy project (no browser: it times the render callback)."""

from __future__ import annotations

import json


def test_viewer_frame_time_times_full_and_preview_frames(toy_fitted_project, tmp_path):
    from benchmarks.viewer_frame_time import main

    out = tmp_path / "frames.json"
    res = main([str(toy_fitted_project), "--resolutions", "32", "--repeats", "1", "--device", "cpu",
                "--out", str(out)])
    assert [(r.kind, r.side) for r in res.rows] == [("full", 32), ("preview", 16)]
    assert all(r.median_s > 0 and r.min_s <= r.median_s and r.repeats == 1 for r in res.rows)
    assert res.device == "cpu" and res.node_state_s > 0 and 0 < res.fov_y_rad < 3.2
    saved = json.loads(out.read_text())
    assert [r["side"] for r in saved["rows"]] == [32, 16] and saved["node_state_s"] == res.node_state_s
