"""benchmarks/garment_tracking.py: the patch residuals and node spread on exact synthetic motions, and the whole
benchmark on a toy Gaussian project with a toy ground-truth garment (the lower half of the body grown 2 %)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch


def _rotation_z(angle: float) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)


def test_a_rigidly_turning_patch_leaves_no_rigid_residual_but_a_translation_residual():
    from benchmarks.garment_tracking import patch_residuals

    gen = torch.Generator().manual_seed(0)
    X = 0.1 * torch.randn(50, 3, generator=gen, dtype=torch.float64)
    frames = torch.stack([X @ _rotation_z(a).T + torch.tensor([a, 0.0, 0.0], dtype=torch.float64)
                          for a in (0.0, 0.3, -0.4, 0.6)])
    trans, rigid = patch_residuals(frames, torch.zeros(50, dtype=torch.long), 1)
    assert float(rigid.max()) < 1e-9
    assert float(trans.mean()) > 0.01
    # two patches each moving by its own translation: no residual for either fit
    shifted = frames.clone()
    shifted[:, :25] = X[:25] + torch.tensor([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.2, 0.0], [0.0, 0.0, 0.3]],
                                            dtype=torch.float64)[:, None]
    shifted[:, 25:] = X[25:]
    trans, rigid = patch_residuals(shifted, (torch.arange(50) >= 25).long(), 2)
    assert float(trans.max()) < 1e-9 and float(rigid.max()) < 1e-9


def test_a_node_that_moves_with_the_garment_has_no_spread_and_a_still_one_has():
    from benchmarks.garment_tracking import node_drift, nodes_on_garment

    F = 5
    garment = torch.stack([torch.tensor([[0.1 * t, 0.0, 0.0], [1.0, 1.0, 1.0]], dtype=torch.float64) for t in range(F)])
    follow = garment[:, :1] + torch.tensor([0.0, 0.0, 0.01], dtype=torch.float64)  # 1 cm above its vertex
    still = torch.tensor([[[0.0, 0.0, 0.01]]], dtype=torch.float64).expand(F, 1, 3)
    far = torch.full((F, 1, 3), 5.0, dtype=torch.float64)
    centers = torch.cat([follow, still, far], 1)  # [F, 3, 3]
    linear = torch.eye(3, dtype=torch.float64).expand(F, 3, 3, 3)
    on = nodes_on_garment(centers, garment)
    assert on.tolist() == [0, 1]  # the far node is not on the garment
    spread = node_drift(centers, linear, garment, on)
    assert spread.shape == (2, F)
    assert float(spread[0].max()) < 1e-12 and float(spread[1].mean()) > 0.05


def test_the_garment_is_measured_in_the_frame_of_the_node_that_draws_it():
    from benchmarks.garment_tracking import drawn_drift

    F = 4
    garment = torch.stack([torch.tensor([[0.1 * t, 0.0, 0.0], [0.1 * t, 0.0, 1.0]], dtype=torch.float64)
                           for t in range(F)])  # two vertices moving alike
    centers = torch.stack([garment[:, 0], torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand(F, 3)], 1)
    linear = torch.eye(3, dtype=torch.float64).expand(F, 2, 3, 3)  # node 0 follows the garment, node 1 stands still
    # Gaussians (2 a node): node 0's first draws vertex 1 (which lies on node 1's centre), node 1's first draws
    # vertex 0; node 1's second sits on vertex 1 but is dead
    means = torch.tensor([[0.0, 0.0, 0.95], [5.0, 5.0, 5.0], [0.0, 0.0, 0.02], [0.0, 0.0, 1.0]], dtype=torch.float64)
    opacity = torch.tensor([0.9, 0.9, 0.9, 0.01], dtype=torch.float64)
    spread = drawn_drift(centers, linear, garment, means, opacity, per_node=2)
    assert spread.shape == (2, F)
    assert float(spread[1].max()) < 1e-12  # drawn by node 0, which follows it
    assert float(spread[0].mean()) > 0.05  # drawn by the still node 1


def test_the_benchmark_measures_a_toy_project(tmp_path):
    from fixtures.toy_capture import toy_motion
    from fixtures.toy_fitted import make_toy_fitted_gaussians

    from avatarctl.body.toy import ToyBody
    from avatarctl.io.gt_geometry import GT_GEOMETRY
    from benchmarks.garment_tracking import main

    proj = make_toy_fitted_gaussians(tmp_path, iters=2, per_node=8)
    cap = tmp_path / "cap"
    body = ToyBody()
    motion = toy_motion(4)
    faces = body.template(motion).faces.numpy()
    verts = body.pose(motion).vertices.numpy()
    (cap / GT_GEOMETRY).parent.mkdir()
    np.savez(cap / GT_GEOMETRY, frame_index=np.arange(4), body_vertices=verts, body_faces=faces,
             garment_vertices=verts * 1.02, garment_faces=faces)
    out = tmp_path / "tracking.json"
    report = main([str(proj), "--patches", "4,8", "--flow", "--tracks", "--json", str(out)])
    assert report.frames >= 1 and report.garment_vertices == verts.shape[1]
    assert [(r.skinning, r.patches) for r in report.residuals] == [
        ("nearest vertex", 4), ("nearest vertex", 8), ("root", 4), ("root", 8)]
    for r in report.residuals:
        assert all(math.isfinite(v) and v >= 0 for v in (r.translation_cm, r.rigid_cm, r.translation_p90_cm))
    assert [d.motion for d in report.drift] == [d.motion for d in report.drawn] == ["learned", "skeleton"]
    assert all(math.isfinite(d.mean_cm) and d.p90_cm >= 0 for d in report.drawn)
    assert report.nodes_on_garment > 0 and all(math.isfinite(d.mean_cm) for d in report.drift)
    assert len(report.nodes) == report.nodes_on_garment
    for d in report.drift:  # where the motion loses the cloth: per training frame and per node on the garment
        assert len(d.frame_median_cm) == len(d.frame_p90_cm) == report.frames
        assert len(d.node_mean_cm) == report.nodes_on_garment
        assert all(p >= m >= 0 for m, p in zip(d.frame_median_cm, d.frame_p90_cm))
        assert math.isclose(sum(d.node_mean_cm) / len(d.node_mean_cm), d.mean_cm, rel_tol=1e-6)
    f = report.flow
    assert f is not None and f.pairs >= 1 and f.vertices > 0
    assert math.isfinite(f.error_px) and f.error_px >= 0 and f.still_error_px == f.motion_px >= 0
    g = report.gaussian_motion  # a Gaussian-field avatar: part 4 measured
    assert g is not None and g.gaussians > 0 and math.isfinite(g.error_px) and g.error_px >= 0
    tracks = report.tracks  # part 5: a few training frames, so only the first gaps from the middle one
    assert tracks is not None and tracks[0].gap == 1 and all(t.gap in (1, 2) for t in tracks)
    for t in tracks:
        assert t.vertices > 0 and 0.0 <= t.tracked <= 1.0 and t.motion_px >= 0
        assert math.isfinite(t.direct_px) and t.direct_px >= 0 and t.direct_p90_px >= t.direct_px
    saved = json.loads(out.read_text())
    assert saved["nodes_on_garment"] == report.nodes_on_garment and len(saved["residuals"]) == 4
    assert saved["flow"]["pairs"] == f.pairs
    assert [t["gap"] for t in saved["tracks"]] == [t.gap for t in tracks]


def test_error_parts_split_a_turn_and_a_flare_of_a_ring():
    """Part 6's split of the tracked surface's error: a ring turned about the up axis errs tangentially, a ring
    widened radially; the hem radius reads the widening."""
    from benchmarks.garment_tracking import error_parts, hem_radius

    a = np.linspace(0, 2 * np.pi, 72, endpoint=False)
    z = np.repeat([0.0, 0.3], 72)  # two rings: the hem (z = 0) and the waist (z = 0.3)
    ring = np.stack([0.3 * np.cos(np.tile(a, 2)), 0.3 * np.sin(np.tile(a, 2)), z], 1)
    up = np.array([0.0, 0.0, 1.0])
    turn = 0.1
    turned = ring @ np.array([[np.cos(turn), -np.sin(turn), 0], [np.sin(turn), np.cos(turn), 0], [0, 0, 1]]).T
    p = error_parts(ring, turned, up)  # the tracked ring lags the true one by 0.1 rad: clockwise, 3 cm at 30 cm
    assert p.tangential == pytest.approx(-100 * 0.3 * np.sin(turn), rel=1e-3)
    assert abs(p.radial) < 0.2 and abs(p.along) < 1e-9
    assert p.hem == pytest.approx(p.waist) == pytest.approx(100 * 2 * 0.3 * np.sin(turn / 2), rel=1e-6)
    flared = ring.copy()
    flared[:72, :2] *= 4 / 3  # the true hem opens to 40 cm; the tracked surface stays at 30
    p = error_parts(ring, flared, up)
    assert p.radial == pytest.approx(-5.0, rel=1e-6) and abs(p.tangential) < 1e-9
    assert p.hem == pytest.approx(10.0) and p.waist == pytest.approx(0.0, abs=1e-9)
    assert hem_radius(ring, up) == pytest.approx(30.0) and hem_radius(flared, up) == pytest.approx(40.0)


def test_part_6_scores_a_fits_tracks_and_tracks_them_again_through(tmp_path):
    """Part 6 on a toy project whose fit/track/tracks.npz holds the true garment: the fit's tracks score ~0 against
    the truth on every frame; `--through` tracks its reference surface again over every frame, split per frame."""
    from fixtures.toy_capture import toy_motion
    from fixtures.toy_fitted import make_toy_fitted_gaussians

    from avatarctl.body.toy import ToyBody
    from avatarctl.io.gt_geometry import GT_GEOMETRY
    from avatarctl.io.project_io import load_project_capture
    from avatarctl.project import Project
    from benchmarks.garment_tracking import main

    proj = make_toy_fitted_gaussians(tmp_path, iters=2, per_node=8)
    body = ToyBody()
    motion = toy_motion(4)
    faces = body.template(motion).faces.numpy()
    garment = body.pose(motion).vertices.numpy() * 1.02
    (tmp_path / "cap" / GT_GEOMETRY).parent.mkdir()
    np.savez(tmp_path / "cap" / GT_GEOMETRY, frame_index=np.arange(4), body_vertices=garment / 1.02,
             body_faces=faces, garment_vertices=garment, garment_faces=faces)
    frames = list(load_project_capture(Project.open(proj)).split.train_frames)
    folder = Project.open(proj).paths.fit / "track"
    folder.mkdir(parents=True, exist_ok=True)
    F = len(frames)
    np.savez(folder / "tracks.npz", frames=np.asarray(frames), vertices=garment[frames].astype(np.float32),
             faces=faces, seen=np.full((F, garment.shape[1]), 2), loss=np.zeros(F), tracked=np.ones(F, bool),
             reference=F // 2, nodes=np.zeros(0, dtype=np.int64))
    plain = main([str(proj), "--patches", "4"]).surface
    assert plain is not None and not plain.through and plain.frames_tracked == F and plain.vertices > 0
    assert max(plain.tracked_cm) < 0.5  # the tracks are the truth (to the 24-point matching)
    assert len(plain.parts) == len(plain.hem_radius_cm) == len(plain.surface_hem_radius_cm) == F
    assert all(abs(p.radial) < 0.5 and abs(p.tangential) < 0.5 for p in plain.parts)
    again = main([str(proj), "--patches", "4", "--through"]).surface
    assert again.through and again.frames_tracked == F and len(again.parts) == F
    assert all(math.isfinite(x) for x in again.tracked_cm + again.surface_hem_radius_cm)
    assert again.tracked_cm[F // 2] == plain.tracked_cm[F // 2]  # the reference frame is not re-tracked


def test_through_tracks_with_the_fits_saved_settings(tmp_path):
    """`--through` re-tracks with the settings fit/track/summary.json says the fit's tracker ran with (lists back to
    tuples, keys this version does not know ignored); today's defaults without a summary."""
    from avatarctl.fit.garment_track import TrackSettings
    from benchmarks.garment_tracking import saved_settings

    path = tmp_path / "summary.json"
    path.write_text(json.dumps({"settings": {"iters": 7, "sigmas": [2.0, 1.0], "gone": 1}}))
    assert saved_settings(path) == TrackSettings(iters=7, sigmas=(2.0, 1.0))
    assert saved_settings(tmp_path / "missing.json") == TrackSettings()
