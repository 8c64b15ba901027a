"""benchmarks/bench.py at toy scale (the sphere body, 8 rays, the cpu-mlp preset): sparse and dense node evaluation
render the same colours, and every figure of the table is there."""

from __future__ import annotations

import json


def test_bench_compares_sparse_and_dense_on_the_toy_body(tmp_path):
    from benchmarks.bench import main

    out = tmp_path / "bench.json"
    res = main(["--device", "cpu", "--body", "toy", "--presets", "cpu-mlp", "--rays-cpu", "8", "--rays-throughput", "8",
                "--repeats", "1", "--steps", "1", "--out", str(out)])
    assert res["body"] == "toy" and res["joints"] == 2
    (c,) = res["comparisons"]
    assert c["preset"] == "cpu-mlp" and c["rays"] == 8 and c["frames"] == 4
    for path in ("sparse", "dense"):
        assert c[path]["step_s"] > 0 and c[path]["peak_bytes"] > 0 and c[path]["samples"] > 0
    assert c["max_abs_rgb_diff"] < 1e-5  # the packed sparse path computes what the dense one does
    assert 0 < c["sparse"]["pairs"] < c["dense"]["pairs"]  # sparse skips (sample, node) pairs outside the supports
    assert res["throughput"]["rays"] == 8 and res["throughput"]["rays_per_s"] > 0
    assert json.loads(out.read_text())["comparisons"][0]["sparse"]["pairs"] == c["sparse"]["pairs"]
