"""`avatarctl eval`'s colour-matched figure (NeRF-W's protocol, issue 51): a separate field in metrics.json and a
separate row in the printed table; it equals the plain figure when the cameras agree and is higher when the held-out
camera is darker (measured on a render that is the truth up to noise: a few steps of a toy fit leave pixels the avatar
does not cover, whose error no colour transform can take out); a training camera with a learned colour transform is
scored through it."""

from __future__ import annotations

import json

import numpy as np
import pytest


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    from fixtures.toy_fitted import make_toy_fitted

    return make_toy_fitted(tmp_path_factory.mktemp("colour_matched"), iters=40)


def test_colour_matched_is_its_own_field_row_and_column(fitted):
    from avatarctl.evaluate.report import EvalMetrics
    from avatarctl.stages import evaluate
    from avatarctl.stages.evaluate import EvalConfig

    agree = evaluate.run(fitted, EvalConfig(split="novel_view", name="agree", device="cpu")).metrics
    cm = agree.colour_matched
    assert cm is not None and cm["images"] == agree.images and "NeRF-W" in cm["protocol"]
    # (how close the two figures are when the cameras agree depends on the avatar: this 40-step toy one is far too
    # rough to say; measured below on a render that is the truth up to noise)
    assert 0 < cm["psnr"] < 100 and 0 < cm["plain_psnr"] < 100
    saved = json.loads((fitted / "eval" / "agree" / "metrics.json").read_text())
    assert EvalMetrics.from_json(saved) == agree and saved["colour_matched"]["psnr"] == cm["psnr"]
    header = (fitted / "eval" / "agree" / "per_frame.csv").read_text().splitlines()[0]
    assert ",pixels,matched_psnr,matched_plain_psnr,refined_psnr,refined_ssim,latent,render_seconds" in header
    assert all(len(g) == 3 for g in cm["gain"].values()) and set(cm["gain"]) == set(agree.views)


def test_matched_score_is_higher_than_plain_for_a_darker_camera_and_equal_when_they_agree():
    """An avatar that renders the truth up to noise: scored against its own camera the two figures agree; against a
    camera that records 30 % darker (and a little green) only the matched one stays high."""
    from avatarctl.evaluate.colour import apply_colour
    from avatarctl.evaluate.metrics import psnr_from_mse
    from avatarctl.stages.evaluate import _matched_score

    rng = np.random.default_rng(0)
    H, W = 48, 40
    alpha = np.zeros((H, W), np.float32)
    alpha[8:40, 10:30] = 1.0  # the subject
    bg = np.zeros(3, np.float32)
    truth = alpha[..., None] * rng.uniform(0.2, 0.9, (H, W, 3)).astype(np.float32)
    render = np.clip(truth + alpha[..., None] * rng.normal(0, 0.03, truth.shape), 0, 1).astype(np.float32)
    mask = np.ones((H, W), bool)
    same = _matched_score(render, alpha, truth, alpha > 0, bg, mask, (0, 0, W, H))
    assert abs(psnr_from_mse(same.mse) - psnr_from_mse(same.plain_mse)) < 0.2
    darker = apply_colour(truth, alpha, bg, np.array([0.7, 0.75, 0.7], np.float32), np.zeros(3, np.float32))
    dark = _matched_score(render, alpha, darker, alpha > 0, bg, mask, (0, 0, W, H))
    assert psnr_from_mse(dark.mse) > psnr_from_mse(dark.plain_mse) + 6.0
    assert np.allclose(dark.gain, [0.7, 0.75, 0.7], atol=0.03)


def test_the_printed_table_has_a_separate_colour_matched_row(fitted):
    from typer.testing import CliRunner

    from avatarctl.cli.app import app

    res = CliRunner().invoke(app, ["eval", str(fitted), "--name", "printed", "--device", "cpu"],
                             env={"COLUMNS": "250"})
    assert res.exit_code == 0, res.output
    rows = [line for line in res.output.splitlines() if "PSNR" in line]
    assert any("colour-matched" in r and "NeRF-W" in r for r in rows)
    assert any("colour-matched" not in r and "dB" in r for r in rows)  # the plain row stays apart


def test_training_views_are_scored_through_their_learned_colour(tmp_path):
    """A fit with colour transforms on: `eval --split train` applies each training camera's transform (changing the
    camera's transform changes its score), held-out views are rendered at identity."""
    import torch

    from fixtures.toy_capture import make_toy_capture

    from avatarctl.fit.checkpoint import load_avatar
    from avatarctl.project import Project
    from avatarctl.stages import evaluate, fit, ingest
    from avatarctl.stages.evaluate import EvalConfig, _as_camera_sees
    from avatarctl.stages.fit import FitRequest
    from avatarctl.stages.ingest import IngestConfig

    cap, proj = make_toy_capture(tmp_path / "cap"), tmp_path / "proj"
    ingest.run(proj, IngestConfig(capture=cap, project=proj, contact_sheet=False))
    fit.run(proj, FitRequest(preset="micro", iters=4, overrides=("val_every=0", "model.colour.enabled=true"),
                             device="cpu"), handle_sigint=False)
    av = load_avatar(Project.open(proj), device="cpu")
    with torch.no_grad():
        av.model.camera_colour.log_gain[1] = -0.5  # cam02 darker than cam00 (centred: cam00 brighter)
    rgb = np.full((4, 4, 3), 0.5, np.float32)
    alpha = np.ones((4, 4), np.float32)
    assert _as_camera_sees(av, "cam02", rgb, alpha, None).mean() < 0.5 < \
        _as_camera_sees(av, "cam00", rgb, alpha, None).mean()
    assert np.array_equal(_as_camera_sees(av, "cam01", rgb, alpha, None), rgb)  # held out, no gains: identity
    gain = np.array([0.5, 1.0, 1.5], np.float32)  # held out, through ingest's gains: on the foreground
    np.testing.assert_allclose(_as_camera_sees(av, "cam01", rgb, alpha, gain)[0, 0], 0.5 * gain, atol=1e-6)
    # a training camera keeps its learned transform whatever gains are passed
    assert np.array_equal(_as_camera_sees(av, "cam02", rgb, alpha, gain), _as_camera_sees(av, "cam02", rgb, alpha,
                                                                                        None))
    m = evaluate.run(proj, EvalConfig(split="train", name="train", device="cpu")).metrics
    assert m.images > 0 and m.colour_matched is not None
