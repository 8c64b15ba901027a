"""benchmarks/gpu_suite.py, the one script of every GPU measurement, run at toy scale on the CPU so it cannot rot."""

from __future__ import annotations

import json


def test_gpu_suite_runs_every_part_at_toy_scale(tmp_path):
    from benchmarks.gpu_suite import PARTS, main

    res = main(["--out", str(tmp_path), "--device", "cpu", "--quick"])
    parts = res["parts"]
    assert set(parts) == set(PARTS)
    bad = {k: v.get("error") for k, v in parts.items() if not v["ok"]}
    assert not bad, bad
    assert parts["parity"]["avatar_render_max_abs_diff"] == 0.0  # cpu against cpu: the same code, the same numbers
    assert parts["parity"]["raster_grad_means_max_abs"] > 0
    assert all(parts["train"][k]["images_per_s"] > 0 for k in ("batch4", "batch16"))
    assert parts["profile"]["per_render"]["by_cpu_time"]
    assert parts["render"]["ms_per_render"] > 0 and parts["render"]["raster_ms"] > 0
    assert parts["raster"]["table"]["rows"]
    assert parts["density"]["ms_per_million_points"] > 0 and parts["density"]["sigma_max_rel_diff_vs_twin"] < 1e-4
    assert parts["track"]["seconds_by_device"]["cpu"] > 0 and parts["track"]["max_vertex_diff_mm_vs_cpu"] == 0.0
    assert json.loads((tmp_path / "gpu_suite.json").read_text())["parts"].keys() == parts.keys()
