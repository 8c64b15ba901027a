"""benchmarks/splat_bench.py at toy scale (200 Gaussians, 32 px, one repeat): a row per backend, the same scene."""

from __future__ import annotations

import json


def test_splat_bench_times_both_backends_on_one_scene(tmp_path, capsys):
    from benchmarks.splat_bench import main

    out = tmp_path / "splat.json"
    res = main(["--device", "cpu", "--sizes", "32:200", "--threads", "1", "--backends", "warp", "torch",
                "--repeats", "1", "--json", str(out)])
    warp, torch_row = res["rows"]
    assert (warp["backend"], torch_row["backend"]) == ("warp", "torch")
    for r in res["rows"]:
        assert (r["side"], r["gaussians"], r["threads"]) == (32, 200, 1)
        assert r["forward_ms"] > 0 and r["backward_ms"] > 0 and r["total_ms"] >= r["forward_ms"]
        assert 0 < r["visible"] <= 200 and r["tile_entries"] >= r["visible"]
    assert (warp["visible"], warp["tile_entries"]) == (torch_row["visible"], torch_row["tile_entries"])
    assert json.loads(out.read_text())["rows"] == res["rows"]
    assert "backward" in capsys.readouterr().out  # the table's header


def test_splat_bench_freezes_the_inputs_it_is_told():
    """`--frozen colors`: the row records it; freezing every input (nothing to differentiate) or an unknown name is
    refused."""
    import pytest

    from benchmarks.splat_bench import run

    (row,) = run("cpu", sizes=((32, 200),), threads=(1,), repeats=1, frozen=("colors",))["rows"]
    assert row["frozen"] == ["colors"] and row["backward_ms"] > 0
    for frozen in (("means", "covars", "colors", "opacities"), ("colours",)):
        with pytest.raises(ValueError, match="proper subset"):
            run("cpu", sizes=((32, 200),), threads=(1,), repeats=1, frozen=frozen)
