"""`avatarctl demo` at the CI-sized preset: synth -> ingest -> fit -> render -> eval end to end.

Not marked slow: ~36 s on 2 lightly loaded cores (it runs in CI either way)."""

from __future__ import annotations

import json
import math

import pytest
from typer.testing import CliRunner

from avatarctl.errors import InputError


def test_demo_refuses_non_empty_out_and_unknown_preset(tmp_path):
    from avatarctl.stages.demo import DemoConfig, run

    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "keep.txt").write_text("mine")
    with pytest.raises(InputError, match="not empty"):
        run(tmp_path / "out", DemoConfig(out=tmp_path / "out", preset="ci"))
    assert (tmp_path / "out" / "keep.txt").read_text() == "mine"
    with pytest.raises(InputError, match="unknown demo preset"):
        DemoConfig(out=tmp_path / "x", preset="huge")
    assert DemoConfig(out=tmp_path / "x", preset="micro").preset == "ci"


@pytest.mark.anny
def test_demo_ci_preset_end_to_end(tmp_path):
    from avatarctl.cli.app import app
    from avatarctl.project import Project
    from avatarctl.render.video import probe_video

    out = tmp_path / "demo"
    res = CliRunner().invoke(app, ["demo", str(out), "--preset", "ci", "--device", "cpu"])
    assert res.exit_code == 0, res.output
    for stage in ("synth", "ingest", "fit", "render orbit", "render novel_pose", "eval novel_view",
                  "eval novel_pose"):
        assert stage in res.output, stage
    assert "fit micro for 20 steps," in res.output  # the ci demo has no time budget: the step count ends its fit
    assert "stopped by" in res.output and "the step count" in res.output
    project = Project.open(out / "project")
    assert [r.stage for r in project.manifest.stages] == ["ingest", "fit", "render", "render", "eval", "eval"]
    for name in ("orbit", "novel_pose"):
        video = out / "project" / "render" / name / "video.mp4"
        assert str(video) in res.output.replace("\n", "")
        assert probe_video(video)["frames"] > 0
    for split in ("novel_view", "novel_pose"):
        m = json.loads((out / "project" / "eval" / f"{split}_bbox" / "metrics.json").read_text())
        assert m["split"] == split and math.isfinite(m["psnr"]) and math.isfinite(m["ssim"])
        assert (out / "project" / "eval" / f"{split}_bbox" / "sheet.png").is_file()
