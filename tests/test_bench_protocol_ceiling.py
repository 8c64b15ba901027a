"""benchmarks/protocol_ceiling.py: the mask-sharp image from a coverage render, and the whole benchmark on a synth
micro capture (2x2 supersampled) after ingest: the re-rendered true scene lines up with the project's ground truth,
and an eval folder whose renders are that ground truth scores as such."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest


def test_mask_sharp_divides_the_coverage_out_and_fills_uncovered_mask_pixels():
    from benchmarks.protocol_ceiling import mask_sharp

    bg = np.array([0.2, 0.4, 0.6], np.float32)
    subject = np.array([0.9, 0.1, 0.3], np.float32)
    cov = np.zeros((4, 5), np.float32)
    cov[1:3, 1:3] = 1.0
    cov[1:3, 3] = 0.25  # a quarter-covered column
    physical = cov[..., None] * subject + (1 - cov[..., None]) * bg
    mask = np.zeros((4, 5), bool)
    mask[1:3, 1:4] = True  # the quarter column counted in the mask
    mask[0, 1] = True  # a mask pixel the subject does not touch (nearest-neighbour resampling)
    out = mask_sharp(physical, cov, mask, bg)
    assert np.allclose(out[mask], subject, atol=1e-5)  # every mask pixel: the subject's own colour
    assert np.allclose(out[~mask], bg)


@pytest.mark.anny
def test_the_benchmark_scores_a_synth_capture(tmp_path):
    synth = pytest.importorskip("avatarctl.synth")
    from avatarctl.evaluate.protocols import ground_truth
    from avatarctl.ingest.config import IngestConfig
    from avatarctl.ingest.pipeline import run_ingest
    from avatarctl.io.project_io import load_project_capture
    from avatarctl.project import Project
    from avatarctl.render.images import write_png
    from benchmarks.protocol_ceiling import main, measure

    cap = tmp_path / "cap"
    synth.synthesize(cap, synth.SynthConfig.preset("micro", seed=0, supersample=2))
    proj = tmp_path / "proj"
    run_ingest(IngestConfig(capture=cap, project=proj))

    r = measure(proj, "novel_pose")
    physical, sharp = r.rows
    assert r.images == 4 and r.views == ["cam01"] and r.supersample == 2 and r.pixels["edge"] > 0
    # the true scene through the capture's cameras, undistorted and compressed as ingest does, agrees with the ground
    # truth away from the edge up to JPEG noise; a camera, frame or undistortion mix-up would leave it far lower
    assert physical.pooled_psnr["inner"] > 36.0
    assert physical.pooled_psnr["edge"] < physical.pooled_psnr["inner"]
    # an edge as hard as the mask: nothing wrong outside the mask, better than the physical render on the edge
    assert sharp.pooled_psnr["edge_out_of_mask"] == 100.0
    assert sharp.pooled_psnr["edge"] > physical.pooled_psnr["edge"] + 1.0
    assert sharp.mean_image_psnr > physical.mean_image_psnr

    # an "eval" whose renders are the ground truth itself: the avatar row scores what PNG rounding leaves
    ev = proj / "eval" / "fake"
    (ev / "renders").mkdir(parents=True)
    c = load_project_capture(Project.open(proj))
    frames, views = list(c.split.test_frames[:2]), list(c.split.test_views)
    for f in frames:
        for v in views:
            write_png(ev / "renders" / f"{f:06d}_{v}.png", ground_truth(c.image(v, f), c.mask(v, f), (0, 0, 0)), None)
    (ev / "metrics.json").write_text(json.dumps({"split": "novel_pose", "protocol": "bbox", "frames": frames,
                                                 "views": views, "background": [0, 0, 0],
                                                 "config": {"bbox_pad": 0.05}}))
    out = tmp_path / "ceiling.json"
    r2 = main([str(proj), "--eval", str(ev), "--json", str(out)])
    assert r2.images == len(frames) * len(views) and [x.avatar for x in r2.rows][-1] == "avatar"
    assert r2.rows[-1].mean_image_psnr > 45.0
    saved = json.loads(out.read_text())
    assert saved["rows"][2]["avatar"] == "avatar" and math.isclose(saved["rows"][2]["mean_image_psnr"],
                                                                    r2.rows[2].mean_image_psnr)
    (ev / "renders" / f"{frames[0]:06d}_{views[0]}.png").unlink()
    with pytest.raises(SystemExit, match="missing"):
        main([str(proj), "--eval", str(ev)])
