"""synth -> ingest -> fit -> load_avatar -> render_view on the smallest synthetic capture (slow: ~1 min)."""

from __future__ import annotations

import numpy as np
import pytest


@pytest.mark.slow
@pytest.mark.anny
def test_synth_ingest_fit_render(tmp_path):
    from avatarctl.fit.checkpoint import load_avatar
    from avatarctl.fit.config import resolve_fit_config
    from avatarctl.fit.loop import fit
    from avatarctl.ingest.config import IngestConfig
    from avatarctl.ingest.pipeline import run_ingest
    from avatarctl.project import Project
    from avatarctl.render.engine import render_view
    from avatarctl.synth import SynthConfig, synthesize

    synthesize(tmp_path / "capture", SynthConfig.preset("micro", 0))
    run_ingest(IngestConfig(capture=tmp_path / "capture", project=tmp_path / "proj", contact_sheet=False))
    project = Project.open(tmp_path / "proj")
    res = fit(project, resolve_fit_config("micro", iters=4, overrides=["val_every=2", "log_every=2"]), device="cpu")
    assert res.step == 4 and res.val is not None and np.isfinite(res.val.psnr)
    av = load_avatar(project)
    frame = av.train_frames[-1]
    motion = av.capture.motion.for_frames([frame])
    state = av.model.node_state(av.conditioning(motion, frames_are_training=True), mode="mean")
    cam = av.capture.cameras[av.capture.split.test_views[0]]
    view = render_view(av.model, state, 0, cam, av.background)
    assert view.rgb.shape == (cam.height, cam.width, 3) and np.isfinite(view.rgb).all()
    assert view.rays > 0 and (view.alpha > 0).any()
