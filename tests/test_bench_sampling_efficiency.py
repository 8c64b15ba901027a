"""benchmarks/sampling_efficiency.py on the fitted toy project (the micro preset trains occupancy grids)."""

from __future__ import annotations

import json


def test_sampling_efficiency_renders_with_and_without_skipping(toy_fitted_project, tmp_path):
    from benchmarks.sampling_efficiency import main

    from avatarctl.fit.config import preset

    out = tmp_path / "sampling.json"
    res = main([str(toy_fitted_project), "--images", "2", "--out", str(out)])
    assert res.images == 2 and set(res.ways) == {"all samples", "occupancy"}
    full, skip = res.ways["all samples"], res.ways["occupancy"]
    assert full.field_samples_per_ray == preset("micro").model.samples_per_ray  # every sample of every ray
    assert 0 < skip.field_samples_per_ray <= full.field_samples_per_ray
    assert full.node_field_evals_per_ray > 0 and full.seconds_per_image > 0 and full.psnr_bbox_vs_gt > 0
    assert full.psnr_vs_all_samples is None and skip.psnr_vs_all_samples > 30  # skipping changes (nearly) nothing
    saved = json.loads(out.read_text())
    assert saved["images"] == 2 and saved["ways"]["occupancy"]["psnr_bbox_vs_gt"] == skip.psnr_bbox_vs_gt
