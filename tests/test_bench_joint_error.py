"""benchmarks/joint_error.py on the fitted toy project: zero against its own fits; a body moved by 5 cm in every
frame gives 5 cm at every joint and vertex, all of it shared by the frames."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import pytest


def test_joint_error_against_own_and_shifted_fits(toy_fitted_project, tmp_path, capsys):
    from benchmarks.joint_error import main, measure

    from avatarctl.body.motion import BodyMotion
    from avatarctl.project import Project

    fits = Path(Project.open(toy_fitted_project).manifest.source.path) / "motion.npz"
    r = main([str(toy_fitted_project), str(fits), "--json", str(tmp_path / "e.json")])
    given = r.errors[0]
    assert given.name == "fits as given" and r.frames > 0 and r.major_joints > 0
    assert given.joint_cm == pytest.approx(0.0, abs=1e-6) and given.vertex_cm == pytest.approx(0.0, abs=1e-6)
    assert json.loads((tmp_path / "e.json").read_text())["frames"] == r.frames
    assert "fits as given  joint error 0.00 cm" in capsys.readouterr().out
    assert r.refined == (r.correction_rms_deg is not None)  # the toy fits are not ground truth: refinement is on

    motion = BodyMotion.load(fits)
    moved = tmp_path / "moved.npz"
    replace(motion, transl=motion.transl + [0.0, 0.05, 0.0]).save(moved)
    shifted = measure(toy_fitted_project, moved).errors[0]
    assert shifted.joint_cm == pytest.approx(5.0, abs=1e-4) and shifted.vertex_cm == pytest.approx(5.0, abs=1e-4)
    assert shifted.shared_cm == pytest.approx(5.0, abs=1e-4) and shifted.scatter_cm == pytest.approx(0.0, abs=1e-4)
