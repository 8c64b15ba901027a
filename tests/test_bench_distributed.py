"""benchmarks/distributed.py at toy scale. One rank: every part but the all-reduce (wall, CPU per step, phases) on
the fitted toy project; two ranks (gloo): the all-reduce alone. A 2-rank fit takes ~30 s here (two spawned
processes importing torch on 2 shared cores), too slow for the fast suite: `--ranks 2 --parts wall` is not run."""

from __future__ import annotations

import json
import math

import pytest


@pytest.fixture
def _restore_threads(monkeypatch):
    """The benchmark sets OMP_NUM_THREADS and torch's thread count for its fits: put both back."""
    import torch

    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    saved = torch.get_num_threads()
    yield
    torch.set_num_threads(saved)


def test_distributed_one_rank_wall_cpu_and_phases(toy_fitted_project, tmp_path, _restore_threads):
    from benchmarks.distributed import main

    out = tmp_path / "dist.json"
    res = main(["--project", str(toy_fitted_project), "--cache", str(tmp_path / "cache"), "--seconds", "0.5",
                "--threads", "1", "--ranks", "1", "--preset", "micro", "--cpu-steps", "2", "--out", str(out)])
    (run,) = res.runs  # --threads 1: the 1-thread and the all-threads run are one run
    assert (run["nproc"], run["threads_per_rank"], run["rays_per_batch"]) == (1, 1, 128)
    assert run["steps"] > 0 and run["steps_per_s"] > 0 and math.isfinite(run["final_mse"])
    assert set(res.cpu_time) == {"n1_cpu_s_per_step"} and math.isfinite(res.cpu_time["n1_cpu_s_per_step"])
    assert [(p["nproc"], p["rays_per_batch"]) for p in res.phases] == [(1, 128), (1, 64)]
    assert all(p["forward_cpu_s"] > 0 and p["backward_cpu_s"] > 0 for p in res.phases)
    assert res.sync == {}  # needs 2 ranks
    saved = json.loads(out.read_text())
    assert saved["ranks"] == [1] and saved["runs"][0]["steps"] == run["steps"] and len(saved["phases"]) == 2


def test_distributed_two_rank_allreduce(toy_fitted_project, tmp_path, _restore_threads):
    from benchmarks.distributed import main

    res = main(["--project", str(toy_fitted_project), "--cache", str(tmp_path / "cache"), "--ranks", "2",
                "--parts", "sync", "--preset", "micro", "--out", str(tmp_path / "dist.json")])
    assert res.runs == () and res.phases == () and res.cpu_time == {}
    assert res.sync["parameters"] > 0 and res.sync["occupancy_cells"] > 0 and res.sync["allreduce_s"] > 0


def test_distributed_rejects_unknown_parts_and_ranks(tmp_path):
    from benchmarks.distributed import main

    for bad in (["--parts", "wall,walls"], ["--ranks", "3"]):
        with pytest.raises(SystemExit):
            main(bad + ["--out", str(tmp_path / "x.json")])
