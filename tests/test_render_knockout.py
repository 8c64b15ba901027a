"""`render --knockout` / `eval --knockout` (paper Fig. 3, the supplement's node-variable table): the trained Δn_i
and/or e_i set to zero at render time, recorded beside the outputs. Toy sphere, seconds."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from avatarctl.errors import InputError


def test_knockout_names_are_validated_and_ordered():
    from avatarctl.stages.evaluate import EvalConfig
    from avatarctl.stages.render import RenderConfig

    assert RenderConfig(knockout=("embedding", "delta-n")).knockout == ("delta-n", "embedding")
    for make in (RenderConfig, EvalConfig):
        with pytest.raises(InputError, match="unknown knockout"):
            make(knockout=("delta_n",))


def test_render_knockout_writes_metadata_and_changes_the_image(toy_fitted_project):
    import cv2

    from avatarctl.stages import render
    from avatarctl.stages.render import RenderConfig

    plain = render.run(toy_fitted_project, RenderConfig(name="ko_plain", frames="train", device="cpu"))
    ko = render.run(toy_fitted_project, RenderConfig(name="ko_both", frames="train", device="cpu",
                                                     knockout=("delta-n", "embedding")))
    rec = json.loads((ko.out_dir / "config.json").read_text())
    assert rec["knockout"] == ["delta-n", "embedding"] and rec["config"]["knockout"] == ["delta-n", "embedding"]
    assert json.loads((plain.out_dir / "config.json").read_text())["knockout"] == []
    a = cv2.imread(str(plain.out_dir / plain.images[0].file))
    b = cv2.imread(str(ko.out_dir / ko.images[0].file))
    assert a.shape == b.shape and np.abs(a.astype(np.float64) - b.astype(np.float64)).max() > 0


def test_render_cli_knockout_and_bad_name(toy_fitted_project):
    from avatarctl.cli.app import app

    ok = CliRunner().invoke(app, ["render", str(toy_fitted_project), "--frames", "train", "--name", "ko_cli",
                                  "--knockout", "embedding", "--device", "cpu"])
    assert ok.exit_code == 0, ok.output
    assert "embedding set to zero" in ok.output
    rec = json.loads((toy_fitted_project / "render" / "ko_cli" / "config.json").read_text())
    assert rec["knockout"] == ["embedding"]
    bad = CliRunner().invoke(app, ["render", str(toy_fitted_project), "--knockout", "nodes", "--device", "cpu"])
    assert bad.exit_code != 0 and "unknown knockout" in bad.output


def test_eval_knockout_is_recorded(toy_fitted_project):
    from avatarctl.stages import evaluate
    from avatarctl.stages.evaluate import EvalConfig

    res = evaluate.run(toy_fitted_project, EvalConfig(split="train", name="ko_eval", knockout=("delta-n",),
                                                      device="cpu", sheet_rows=0))
    m = json.loads((res.out_dir / "metrics.json").read_text())
    assert m["config"]["knockout"] == ["delta-n"] and np.isfinite(m["psnr"])
