"""benchmarks/profile_step.py at toy scale (so it cannot rot: it broke once when pose refinement became 'auto')."""

from __future__ import annotations


def test_profile_step_profiles_a_gaussian_step_of_a_toy_project(toy_gaussian_project):
    from benchmarks.profile_step import main

    res = main([str(toy_gaussian_project), "model.field=gaussians", "model.gaussians.per_node=24", "--preset",
                "micro", "--warmup", "1", "--steps", "2", "--rows", "5"])
    assert res.ms_per_step > 0
    assert res.stats["images"] > 0 and res.stats["gaussians"] == res.stats["gaussians"] // 24 * 24 > 0
    assert "aten::" in res.table
