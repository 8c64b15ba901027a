"""The synth presets of the paper's other settings (issue 14): `monocular` (one training camera, the subject turning
in place in an A-pose, evaluation-only cameras) and `tight` (no skirt). Small overrides keep each capture to seconds."""

from __future__ import annotations

import json

import numpy as np
import pytest

from avatarctl.errors import InputError


def test_preset_fields_and_view_rules():
    from avatarctl.synth import SynthConfig
    from avatarctl.synth.capture import split_views

    mono, tight = SynthConfig.preset("monocular"), SynthConfig.preset("tight")
    assert (mono.train_views, mono.motion, mono.garment) == (1, "turn", "none")
    assert (tight.train_views, tight.motion, tight.garment) == (0, "choreography", "none")
    names = [f"cam{i:02d}" for i in range(6)]
    assert split_views(names[:4], 1) == (["cam00"], ["cam01", "cam02", "cam03"])
    assert split_views(names, 0) == (["cam00", "cam02", "cam03", "cam05"], ["cam01", "cam04"])  # 4 train, as ZJU
    for bad in (dict(train_views=4), dict(garment="dress"), dict(motion="dance")):
        with pytest.raises(InputError, match="invalid synth config"):
            SynthConfig.preset("monocular", **bad)


@pytest.fixture(scope="module")
def mono_capture(tmp_path_factory):
    from avatarctl.synth import SynthConfig, synthesize

    out = tmp_path_factory.mktemp("mono") / "cap"
    synthesize(out, SynthConfig.preset("monocular", size=48, train_frames=8, test_frames=2, supersample=1))
    return out


@pytest.mark.anny
def test_monocular_capture_split_motion_and_no_garment(mono_capture):
    from avatarctl.body.motion import BodyMotion

    split = json.loads((mono_capture / "split.json").read_text())
    assert split["train_views"] == ["cam00"] and split["test_views"] == ["cam01", "cam02", "cam03"]
    assert split["train_frames"] == list(range(8)) and split["test_frames"] == [8, 9]
    info = json.loads((mono_capture / "capture.json").read_text())
    assert info["garment"]["type"] == "none" and info["garment"]["particles"] == 0
    with np.load(mono_capture / "gt" / "geometry.npz") as g:
        assert g["garment_vertices"].shape == (10, 0, 3) and g["garment_faces"].shape == (0, 3)
    # the subject turns in place: the root's heading sweeps (n-1)/n of a full turn over the n training frames
    motion = BodyMotion.load(mono_capture / "motion.npz")
    R = np.asarray(motion.pose_parameters)[:8, 0, :3, :3]
    heading = np.unwrap(np.arctan2(R[:, 1, 0], R[:, 0, 0]))
    assert np.degrees(heading[-1] - heading[0]) == pytest.approx(360 * 7 / 8, abs=2.0)
    assert np.all(np.diff(heading) > 0)
    assert np.abs(np.asarray(motion.pose_parameters)[:8, 0, :2, 3]).max() < 1e-6  # in place


@pytest.mark.anny
def test_monocular_fit_reads_only_the_training_camera_and_eval_scores_the_others(mono_capture, tmp_path,
                                                                                   monkeypatch):
    from avatarctl.fit.data import FrameStore
    from avatarctl.io.project_io import load_split
    from avatarctl.project import Project
    from avatarctl.stages import evaluate, fit, ingest
    from avatarctl.stages.evaluate import EvalConfig
    from avatarctl.stages.fit import FitRequest
    from avatarctl.stages.ingest import IngestConfig

    proj = tmp_path / "proj"
    ingest.run(proj, IngestConfig(capture=mono_capture, project=proj))
    split = load_split(Project.open(proj).paths.split)
    assert split.train_views == ["cam00"] and split.test_views == ["cam01", "cam02", "cam03"]
    read: set[str] = set()
    load = FrameStore._load

    def recording(self, cam, frame):
        read.add(cam)
        return load(self, cam, frame)

    monkeypatch.setattr(FrameStore, "_load", recording)
    fit.run(proj, FitRequest(preset="micro", iters=3, overrides=("val_pairs=0",), device="cpu"), handle_sigint=False)
    assert read == {"cam00"}
    for split_name, frames in (("novel_view", list(range(0, 8, 4))), ("novel_pose", [8])):
        res = evaluate.run(proj, EvalConfig(split=split_name, every=4, device="cpu", sheet_rows=0))
        assert res.metrics.views == ["cam01", "cam02", "cam03"] and res.metrics.frames == frames
