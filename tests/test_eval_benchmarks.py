"""Named benchmark protocols (`avatarctl.evaluate.benchmarks`) through ingest (`avatarctl.ingest.benchmark`) and
eval: the records themselves, the `mpmavatar` pixel rule, a toy ActorsHQ capture (a partial download: a few frames
of each range) ingested, fitted (micro) and scored under its protocol, and the one-line refusals."""

from __future__ import annotations

import json

import numpy as np
import pytest
from fixtures.actorshq import make_toy_actorshq
from fixtures.cli_errors import assert_one_line_error
from typer.testing import CliRunner

from avatarctl.cli.app import app
from avatarctl.errors import InputError

A1 = "actorshq-physavatar-a1s1"
FRAMES = (460, 461, 462, 660, 661)  # three of the protocol's training frames, two of its test frames


def test_every_protocol_is_well_formed():
    from avatarctl.evaluate.benchmarks import BENCHMARKS
    from avatarctl.io.detect import FORMATS

    assert BENCHMARKS
    for name, p in BENCHMARKS.items():
        assert name == p.name == p.name.lower() and p.dataset in FORMATS
        train, test = p.train_frame_numbers(), p.test_frame_numbers()
        assert train and test and not set(train) & set(test), name
        assert p.train_views is None or not set(p.train_views) & set(p.test_views), name
        assert p.comparable_with and p.traps, name


def test_the_actorshq_protocols_are_physavatars_setting():
    from avatarctl.evaluate.benchmarks import benchmark, for_dataset

    assert for_dataset("actorshq") == [f"actorshq-physavatar-{s}" for s in ("a1s1", "a2s1", "a3s1", "a6s1")]
    p = benchmark(A1)
    assert p.train_frame_numbers() == list(range(460, 660)) and p.test_frame_numbers() == list(range(660, 860))
    assert p.test_views == ("Cam007", "Cam127") and p.train_views is None and p.cameras == 160
    assert (p.scale, p.background, p.pixels, p.split, p.sequence) == (0.25, (0.0, 0.0, 0.0), "mpmavatar",
                                                                      "novel_pose", "Actor01/Sequence1")
    assert any("32.0 dB" in c for c in p.comparable_with)
    assert len(benchmark("actorshq-physavatar-a3s1").test_frame_numbers()) == 150
    with pytest.raises(InputError, match="unknown benchmark protocol 'actorshq'"):
        benchmark("actorshq")


def test_mpmavatar_pixels_erode_blur_and_cut_white():
    from avatarctl.evaluate.protocols import mpmavatar_images, mpmavatar_weights

    mask = np.zeros((40, 40), bool)
    mask[10:30, 10:30] = True
    w = mpmavatar_weights(mask)
    # eroded to [15, 25), blurred 2 px either side of that edge
    assert w[:, :13].max() == 0 and w[:, 13].max() > 0 and 0 < w[20, 15] < 1
    assert w[17:23, 17:23].min() == pytest.approx(1.0) and w.max() <= 1.0
    pred = np.full((40, 40, 3), 0.5, np.float32)
    gt = pred.copy()
    pred[20, 20] = 0.95  # a near-white pixel: zeroed
    gt[:, 21:] = [0.2, 0.4, 0.6]
    p, g = mpmavatar_images(pred, gt, mask)
    assert p[20, 20].tolist() == [0, 0, 0] and np.allclose(p[20, 19], 0.5) and np.allclose(g[20, 22], [.2, .4, .6])
    assert not p[:, :10].any() and not g[:, :10].any()  # outside the mask both are black
    assert pred[20, 20, 0] == np.float32(0.95)  # inputs untouched


def _ingest(tmp_path, frames=FRAMES, **kw):
    from avatarctl.stages import ingest
    from avatarctl.stages.ingest import IngestConfig

    scale_dir = make_toy_actorshq(tmp_path / "cap", frames=frames, size=64)
    proj = tmp_path / "proj"
    return scale_dir, proj, ingest.run(proj, IngestConfig(capture=scale_dir, project=proj, benchmark=A1,
                                                          contact_sheet=False, **kw))


def test_ingest_fit_and_eval_under_a_named_protocol(tmp_path):
    from avatarctl.io.project_io import load_benchmark, load_project_capture
    from avatarctl.project import Project
    from avatarctl.stages import evaluate, fit
    from avatarctl.stages.evaluate import EvalConfig
    from avatarctl.stages.fit import FitRequest

    _, proj, res = _ingest(tmp_path)
    assert res.frames == list(FRAMES) and res.cameras == ["Cam001", "Cam007", "Cam050", "Cam127"]
    assert any(n.startswith(f"benchmark {A1}") for n in res.notes)
    assert any("not comparable" in w and "frames: 5 of the protocol's 400" in w for w in res.warnings)
    project = Project.open(proj)
    split = load_project_capture(project).split
    assert (split.train_frames, split.test_frames) == ([460, 461, 462], [660, 661])
    assert (split.train_views, split.test_views) == (["Cam001", "Cam050"], ["Cam007", "Cam127"])
    rec = load_benchmark(project)
    assert (rec.name, rec.resize, rec.frames, rec.frames_expected) == (A1, 1.0, 5, 400)
    assert rec.partial == ["frames: 5 of the protocol's 400", "cameras: 4 of the protocol's 160"]
    assert "ingest/benchmark.json" in project.last("ingest").outputs
    assert project.last("ingest").config["benchmark"] == A1

    fit.run(proj, FitRequest(preset="micro", iters=2, overrides=("val_every=2", "log_every=2"), device="cpu"),
            handle_sigint=False)
    # the default eval scores under the project's protocol: its split, views, pixels and background
    er = evaluate.run(proj, EvalConfig(device="cpu", sheet_rows=0))
    m = er.metrics
    assert er.out_dir.name == "novel_pose_mpmavatar" and (m.split, m.protocol) == ("novel_pose", "mpmavatar")
    assert (m.frames, m.views, m.background) == ([660, 661], ["Cam007", "Cam127"], [0.0, 0.0, 0.0])
    assert m.benchmark == A1 and any("MPMAvatar" in c for c in m.comparable_with)
    assert m.not_comparable == rec.partial and m.config["benchmark"] == A1
    assert m.lpips is None and m.lpips_reason  # absent here, and said why
    assert 0 < m.psnr < 100 and np.isfinite(m.ssim) and er.warnings == []
    saved = json.loads((er.out_dir / "metrics.json").read_text())
    assert saved["benchmark"] == A1 and saved["not_comparable"] == rec.partial

    # an explicit split or protocol scores outside the protocol, and says nothing of it
    plain = evaluate.run(proj, EvalConfig(split="novel_view", protocol="full", device="cpu", sheet_rows=0,
                                          benchmark="none"))
    assert plain.metrics.benchmark is None and plain.metrics.comparable_with is None
    assert plain.metrics.views == ["Cam007", "Cam127"] and plain.metrics.frames == [460, 461, 462]
    with pytest.raises(InputError, match="ingested with --benchmark actorshq-physavatar-a1s1, not"):
        evaluate.run(proj, EvalConfig(device="cpu", benchmark="actorshq-physavatar-a2s1"))

    # the CLI prints the protocol, what it is comparable with and why it is not
    out = CliRunner().invoke(app, ["eval", str(proj), "--device", "cpu", "--name", "cli", "--sheet", "0"])
    assert out.exit_code == 0, out.output
    assert A1 in out.output and "not comparable" in out.output and "comparable with" in out.output
    assert "LPIPS" in out.output and "absent" in out.output


def test_eval_names_a_fit_background_the_protocol_overrides(tmp_path):
    from avatarctl.stages import evaluate, fit
    from avatarctl.stages.evaluate import EvalConfig
    from avatarctl.stages.fit import FitRequest

    _, proj, _ = _ingest(tmp_path, frames=(460, 660))
    fit.run(proj, FitRequest(preset="micro", iters=1, overrides=("background=1,1,1",), device="cpu"),
            handle_sigint=False)
    er = evaluate.run(proj, EvalConfig(device="cpu", sheet_rows=0))
    assert er.metrics.background == [0.0, 0.0, 0.0]
    assert er.warnings == [f"the avatar was fitted over background 1,1,1; benchmark {A1} renders and composites over "
                           "0,0,0: scored over 0,0,0"]


@pytest.mark.parametrize("setup, args, needles", [
    # the protocol of another sequence
    (dict(recording="Actor02/Sequence1"), [], ("is for Actor01/Sequence1; this capture is Actor02/Sequence1",
                                               "actorshq-physavatar-a2s1")),
    # a partial download without any test frame
    (dict(frames=(460, 461)), [], ("none of the test frames 660:860",)),
    # narrowed to training frames only
    (dict(), ["--frames", "460:462"], ("--frames 460:462 keeps none of the test frames",)),
    # the held-out cameras left out
    (dict(), ["--views", "Cam001,Cam050,Cam127"], ("leaves out the held-out camera(s) Cam007",)),
    (dict(cams=("Cam001", "Cam002", "Cam127")), [], ("lacks the held-out camera(s) Cam007",)),
    # images smaller than the protocol's scale (the 8x down-sampling)
    (dict(scale="8x"), [], ("scores images at 0.25 of the release's resolution; these are at 0.125",)),
    (dict(), ["--resize", "0.5"], ("--resize and --benchmark", "both set the image scale")),
    (dict(), ["--benchmark", "nope"], ("unknown benchmark protocol 'nope'", A1)),
])
def test_ingest_refuses_a_capture_that_is_not_the_protocols(tmp_path, setup, args, needles):
    kw = dict(frames=FRAMES) | setup
    scale_dir = make_toy_actorshq(tmp_path / "cap", **kw)
    proj = tmp_path / "proj"
    if "--benchmark" not in args:
        args = args + ["--benchmark", A1]
    res = CliRunner().invoke(app, ["ingest", str(scale_dir), str(proj), "--no-contact-sheet", *args])
    assert_one_line_error(res, proj, *needles)


def test_a_benchmark_of_another_dataset_is_refused(tmp_path):
    from fixtures.toy_capture import make_toy_capture

    cap, proj = make_toy_capture(tmp_path / "cap"), tmp_path / "proj"
    res = CliRunner().invoke(app, ["ingest", str(cap), str(proj), "--benchmark", A1])
    assert_one_line_error(res, proj, f"--benchmark {A1} is for actorshq captures; this capture is easymocap")


def test_eval_refuses_a_benchmark_the_project_was_not_ingested_with(toy_fitted_project):
    res = CliRunner().invoke(app, ["eval", str(toy_fitted_project), "--benchmark", A1, "--device", "cpu"])
    assert res.exit_code == 2 and f"not ingested with --benchmark {A1}" in res.output
    res = CliRunner().invoke(app, ["eval", str(toy_fitted_project), "--benchmark", A1, "--split", "train"])
    assert res.exit_code == 2 and "sets the split and the protocol" in res.output
