"""Named benchmark protocols (`avatarctl.evaluate.benchmarks`) through ingest (`avatarctl.ingest.benchmark`) and
eval: the records themselves, the `mpmavatar` pixel rule, a toy ActorsHQ capture (a partial download: a few frames
of each range) ingested, fitted (micro) and scored under its protocol, and the one-line refusals."""

from __future__ import annotations

import json

import cv2
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
        assert train and test, name
        if p.split == "novel_view":  # the held-out cameras at training frames
            assert set(test) <= set(train) and p.test_sequence is None, name
        elif p.test_sequence is None:  # new poses of the same recording
            assert not set(train) & set(test), name
        else:  # new poses of another recording: its frame numbers may be the training ones
            assert p.sequence and p.test_sequence != p.sequence, name
        assert p.test_sequence or p.train_views is None or not set(p.train_views) & set(p.test_views), name
        assert p.comparable_with and p.traps, name


@pytest.mark.parametrize("change, needle", [
    (dict(split="novel_view", test_frames="100:110"), "novel_view test frames must be training frames"),
    (dict(train_frames="0:10", test_frames="5:15"), "novel_pose test frames must not be training frames"),
    (dict(train_views=("Cam001", "Cam007")), "a held-out view is also a training view"),
    (dict(test_sequence="Actor01/Sequence1"), "a test_sequence is another recording"),
])
def test_a_malformed_protocol_is_refused(change, needle):
    from dataclasses import replace

    from avatarctl.evaluate.benchmarks import benchmark

    with pytest.raises(ValueError, match=needle):
        replace(benchmark(A1), **change)


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
    # the 4D-DRESS branch of eval.py: the same mask product, the near-white pixel kept
    p2, g2 = mpmavatar_images(pred, gt, mask, white_cut=False)
    assert np.allclose(p2[20, 20], 0.95) and np.array_equal(g2, g) and np.allclose(p2[20, 19], 0.5)


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


# --- DNA-Rendering (novel_view: the held-out cameras at training frames) -------------------------------------------
DNA = "dna_rendering-seqavatar"
DNA_IDS = (0, 2, 48, 50, 52, 54, 56, 58)  # two training cameras and the six held-out ones


def test_dna_rendering_scores_the_protocols_test_frames_from_its_held_out_cameras(random_smplx, tmp_path):
    from fixtures.dataset_layouts import make_dna_rendering_capture

    from avatarctl.io.project_io import load_benchmark, load_project_capture
    from avatarctl.project import Project
    from avatarctl.stages import evaluate, fit, ingest
    from avatarctl.stages.evaluate import EvalConfig
    from avatarctl.stages.fit import FitRequest
    from avatarctl.stages.ingest import IngestConfig

    cap = make_dna_rendering_capture(tmp_path / "0007_04", random_smplx[1], frames=range(7), size=64,
                                     camera_ids=DNA_IDS)
    proj = tmp_path / "proj"
    res = ingest.run(proj, IngestConfig(capture=cap.root, project=proj, body_model_path=random_smplx[0],
                                        benchmark=DNA, contact_sheet=False))
    held_out = ["48", "50", "52", "54", "56", "58"]
    assert res.frames == list(range(7))  # training frames 0:100 that the capture holds; the test frames among them
    split = load_project_capture(Project.open(proj)).split
    assert (split.train_frames, split.test_frames) == (list(range(7)), [])  # no novel-pose frames
    assert (split.train_views, split.test_views) == (["00", "02"], held_out)
    rec = load_benchmark(Project.open(proj))
    assert rec.partial == ["frames: 7 of the protocol's 100", "training cameras: 2 of the protocol's 24"]
    assert rec.resize == 0.25 and rec.role == "both"

    fit.run(proj, FitRequest(preset="micro", iters=2, overrides=("val_every=0",), device="cpu"), handle_sigint=False)
    m = evaluate.run(proj, EvalConfig(device="cpu", sheet_rows=0)).metrics
    # frames 0:100:5 held here (0 and 5, not 1-4 or 6), from the six held-out cameras, at training frames (z = mu)
    assert (m.split, m.protocol, m.benchmark) == ("novel_view", "full", DNA)
    assert (m.frames, m.views, m.images, m.latent) == ([0, 5], held_out, 12, "mean")
    assert m.image_size == [20, 18] and 0 < m.psnr < 100 and m.not_comparable == rec.partial
    narrowed = evaluate.run(proj, EvalConfig(device="cpu", sheet_rows=0, frames="5:7", name="n")).metrics
    assert narrowed.frames == [5] and any("eval frames narrowed" in r for r in narrowed.not_comparable)
    plain = evaluate.run(proj, EvalConfig(device="cpu", sheet_rows=0, benchmark="none", protocol="full")).metrics
    assert plain.frames == list(range(7))  # outside the protocol: every training frame


# --- 4D-DRESS (novel_pose on another take of the outfit: two projects) --------------------------------------------
DRESS = "4d_dress-mpmavatar-00170"


@pytest.fixture(scope="module")
def dress_projects(random_smplx, tmp_path_factory):
    """(capture root, training-take project P, fitted; test-take project Q): Take1 frames 21-23, Take5 frames 21-22
    (the same frame numbers, another motion)."""
    from fixtures.dataset_layouts import make_four_d_dress_take

    from avatarctl.stages import fit, ingest
    from avatarctl.stages.fit import FitRequest
    from avatarctl.stages.ingest import IngestConfig

    root = tmp_path_factory.mktemp("dress")
    take1 = make_four_d_dress_take(root / "00170" / "Inner" / "Take1", random_smplx[1], frames=(21, 22, 23),
                                   extra_image_frame=None)
    take5 = make_four_d_dress_take(root / "00170" / "Inner" / "Take5", random_smplx[1], frames=(21, 22),
                                   extra_image_frame=None, seed=9)
    projects = {}
    for name, take in (("P", take1), ("Q", take5)):
        projects[name] = root / name
        ingest.run(projects[name], IngestConfig(capture=take.root, project=projects[name],
                                                body_model_path=random_smplx[0], benchmark=DRESS,
                                                contact_sheet=False))
    fit.run(projects["P"], FitRequest(preset="micro", iters=2, overrides=("val_every=0",), device="cpu"),
            handle_sigint=False)
    return root, projects["P"], projects["Q"], take5


def test_four_d_dress_trains_on_one_take_and_scores_another(dress_projects, monkeypatch):
    from avatarctl.evaluate.metrics import psnr_from_mse
    from avatarctl.evaluate.protocols import ground_truth, mpmavatar_images
    from avatarctl.io.project_io import load_benchmark, load_project_capture, read_frame, read_mask
    from avatarctl.project import Project
    from avatarctl.stages import evaluate
    from avatarctl.stages.evaluate import EvalConfig

    root, P, Q, take5 = dress_projects
    p, q = load_project_capture(Project.open(P)), load_project_capture(Project.open(Q))
    assert (p.split.train_frames, p.split.test_frames) == ([21, 22, 23], [])
    assert p.split.train_views == ["0004", "0028", "0052", "0076"] and p.split.test_views == []  # 0004 trains too
    assert q.frames == [21, 22] and list(q.cameras) == ["0004"]  # the test take: its test frames and view only
    assert (q.split.train_frames, q.split.test_frames, q.split.test_views) == ([], [21, 22], ["0004"])
    rp, rq = load_benchmark(Project.open(P)), load_benchmark(Project.open(Q))
    assert (rp.role, rp.sequence, rq.role, rq.sequence) == ("train", "00170/Inner/Take1", "test",
                                                            "00170/Inner/Take5")

    driven = []  # the body fits the avatar is driven with
    state_of = evaluate.frame_node_state

    def spy(avatar, one, frame, is_train, latent, seed, held_out=None):
        assert held_out is None  # another recording's frames: never the fit's held-out poses of this one
        driven.append((frame, is_train, one.global_orient[0].copy()))
        return state_of(avatar, one, frame, is_train, latent, seed, held_out)

    monkeypatch.setattr(evaluate, "frame_node_state", spy)
    er = evaluate.run(P, EvalConfig(device="cpu", sheet_rows=0, test_project=str(Q), save_images=True))
    m = er.metrics
    assert (m.split, m.protocol, m.benchmark, m.latent) == ("novel_pose", "mpmavatar_4d_dress", DRESS, "novel")
    assert (m.frames, m.views, m.test_project) == ([21, 22], ["0004"], str(Q.resolve()))
    assert m.config["test_project"] == str(Q) and m.not_comparable == rp.partial + [
        f"test project: {r}" for r in rq.partial]
    for (frame, is_train, orient), k in zip(driven, (0, 1)):  # Take5's fits, as novel poses
        assert frame == take5.frames[k] and not is_train
        assert np.allclose(orient, take5.motion.global_orient[k], atol=1e-5)
    # the score is against Take5's images (Take1's at the same frame numbers would score otherwise)
    for s in er.scores:
        pred = cv2.imread(str(er.out_dir / "renders" / f"{s.frame:06d}_0004.png"))[..., ::-1] / np.float32(255)
        own = []
        for proj in (Q, P):
            mask = read_mask(Project.open(proj), "0004", s.frame)
            a, b = mpmavatar_images(pred, ground_truth(read_frame(Project.open(proj), "0004", s.frame), mask,
                                                       (0, 0, 0)), mask, white_cut=False)
            own.append(psnr_from_mse(float(((a - b) ** 2).mean())))
        assert abs(own[0] - s.psnr) < 0.2 < abs(own[1] - s.psnr), (own, s.psnr)


def test_four_d_dress_refusals(dress_projects, random_smplx, tmp_path):
    import shutil

    from avatarctl.project import Project
    from avatarctl.stages import ingest
    from avatarctl.stages.evaluate import EvalConfig, resolve_benchmark
    from avatarctl.stages.ingest import IngestConfig

    root, P, Q, take5 = dress_projects

    def eval_error(*args):
        res = CliRunner().invoke(app, ["eval", str(P), "--device", "cpu", "--sheet", "0", *args])
        lines = [ln for ln in res.output.strip().splitlines() if ln.startswith("error:")]
        assert res.exit_code == 2 and len(lines) == 1 and "->" in lines[0], res.output
        return lines[0]

    assert "scores another recording (00170/Inner/Take5)" in eval_error()  # no --test-project
    assert "--test-project is 00170/Inner/Take1, not the test recording 00170/Inner/Take5" in eval_error(
        "--test-project", str(P))
    assert "this project has no benchmark" in eval_error("--test-project", str(Q), "--benchmark", "none")
    plain = tmp_path / "plain"  # the test take ingested without the protocol
    ingest.run(plain, IngestConfig(capture=take5.root, project=plain, body_model_path=random_smplx[0],
                                   contact_sheet=False))
    assert f"--test-project was ingested with no benchmark, not {DRESS}" in eval_error("--test-project", str(plain))
    with pytest.raises(InputError, match=r"the project is the test recording \(00170/Inner/Take5\)"):
        resolve_benchmark(Project.open(Q), EvalConfig(test_project=str(P)))

    # ingest: another subject's protocol, and a take whose folders do not say which take it is
    res = CliRunner().invoke(app, ["ingest", str(take5.root), str(tmp_path / "x"), "--benchmark",
                                   "4d_dress-mpmavatar-00185", "--body-model-path", str(random_smplx[0])])
    assert_one_line_error(res, tmp_path / "x", "is for 00185/Inner/Take1 and 00185/Inner/Take7; this capture is "
                                               "00170/Inner/Take5", f"use {DRESS}")
    shutil.copytree(take5.root, tmp_path / "my_take")
    res = CliRunner().invoke(app, ["ingest", str(tmp_path / "my_take"), str(tmp_path / "y"), "--benchmark", DRESS,
                                   "--body-model-path", str(random_smplx[0])])
    assert_one_line_error(res, tmp_path / "y", "this capture's folders do not say which it is", "00170/Inner/Take1")


def test_test_project_is_refused_without_a_two_recording_protocol(toy_fitted_project, tmp_path):
    res = CliRunner().invoke(app, ["eval", str(toy_fitted_project), "--test-project", str(tmp_path), "--device",
                                   "cpu"])
    assert res.exit_code == 2 and "--test-project is for a benchmark whose test frames are another recording" \
        in res.output
