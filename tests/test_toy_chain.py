"""The whole chain ingest -> fit -> render -> eval on the toy sphere body, in seconds and without anny."""

from __future__ import annotations

import json
import math
import sys
import time

import numpy as np
from fixtures.toy_capture import make_toy_capture

from avatarctl.project import Project


def test_ingest_fit_render_eval_on_the_toy_body(tmp_path, monkeypatch):
    from avatarctl.stages import evaluate, fit, ingest, render
    from avatarctl.stages.evaluate import EvalConfig
    from avatarctl.stages.fit import FitRequest
    from avatarctl.stages.ingest import IngestConfig
    from avatarctl.stages.render import RenderConfig

    monkeypatch.setitem(sys.modules, "anny", None)  # any import of anny fails: this chain must not need it
    t0 = time.perf_counter()
    cap, proj = make_toy_capture(tmp_path / "cap"), tmp_path / "proj"
    seen = []
    ing = ingest.run(proj, IngestConfig(capture=cap, project=proj), progress=seen.append)
    assert ing.body_model == "toy" and ing.frames == [0, 1, 2, 3] and ing.vertices_inside_masks > 0.9
    fr = fit.run(proj, FitRequest(preset="micro", iters=4, overrides=("val_every=2", "log_every=2"), device="cpu"),
                 progress=seen.append, handle_sigint=False)
    assert fr.step == 4 and math.isfinite(fr.losses["total"]) and fr.val is not None
    # the checkpoint carries the novel-pose latent of the preset (model.novel_latent = "train_mean"): mean training mu
    import torch

    from avatarctl.fit.checkpoint import load_avatar

    av = load_avatar(Project.open(proj), device="cpu")
    frames = sorted(av.train_frames)
    mu = av.model.node_state(av.conditioning(av.capture.motion.for_frames(frames), True),
                             "mean").mu
    assert av.model.cfg.novel_latent == "train_mean" and av.model.latent.latent_mean.abs().sum() > 0
    assert torch.allclose(av.model.latent.latent_mean, mu.mean(0), atol=1e-5)
    rr = render.run(proj, RenderConfig(name="toy", frames="0:4:3", device="cpu"), progress=seen.append)
    assert [(im.frame, im.latent) for im in rr.images] == [(0, "mean"), (3, "novel")]
    assert all(im.rays > 0 for im in rr.images) and rr.video.is_file()
    er = evaluate.run(proj, EvalConfig(split="novel_view", device="cpu"), progress=seen.append)
    assert er.metrics.images == 6 and er.metrics.model.label == "full model" and 0 < er.psnr < 100
    assert er.metrics.to_json() == json.loads((er.out_dir / "metrics.json").read_text())
    assert [r.stage for r in Project.open(proj).manifest.stages] == ["ingest", "fit", "render", "eval"]
    # one progress shape from every stage, ending at its total
    assert {p.stage for p in seen} == {"ingest", "fit", "render", "eval"}
    for stage in ("ingest", "fit", "render", "eval"):
        last = [p for p in seen if p.stage == stage][-1]
        assert last.done == last.total
    assert np.isfinite(er.metrics.ssim)
    assert time.perf_counter() - t0 < 120, "the toy chain should take seconds"
