"""`avatarctl synth` imperfections (issue 51): each changes what it should and nothing else, against the clean twin.

The captures are the micro preset cut to 3 + 2 frames without the skirt (seconds each): a clean one and one per
imperfection, all from the same seed.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

cv2 = pytest.importorskip("cv2")

SMALL = dict(train_frames=3, test_frames=2, garment="none")


# ---- the pure functions (no anny) -----------------------------------------------------------------------------------
def test_camera_gains_are_seeded_and_share_their_draws_across_spreads():
    from avatarctl.synth.imperfections import camera_gains

    a = camera_gains(3, 4, 0.25, 0.0)
    assert a.shape == (4, 3) and np.allclose(a[:, 0], a[:, 1]) and np.allclose(a[:, 0], a[:, 2])  # exposure: grey
    assert np.allclose(camera_gains(3, 4, 0.5, 0.0), a ** 2)  # the same draws, twice the stops
    assert np.allclose(camera_gains(3, 4, 0.0, 0.0), 1.0)
    wb = camera_gains(3, 4, 0.0, 0.1)
    assert not np.allclose(wb[:, 0], wb[:, 1]) and np.allclose(camera_gains(3, 4, 0.25, 0.1), a * wb)
    assert not np.allclose(camera_gains(4, 4, 0.25, 0.0), a)


def test_sensor_image_scales_adds_noise_and_clips():
    from avatarctl.synth.imperfections import sensor_image

    img = np.full((200, 200, 3), 0.5, np.float32)
    out = sensor_image(img, np.array([0.8, 1.0, 1.2]), 0.0, None)
    assert np.allclose(out[0, 0], [0.4, 0.5, 0.6])
    noisy = sensor_image(img, np.ones(3), 0.02, np.random.default_rng(0))
    assert abs(float((noisy - img).std()) - 0.02) < 0.001 and abs(float((noisy - img).mean())) < 0.001
    assert sensor_image(np.ones((2, 2, 3), np.float32), np.full(3, 2.0), 0.0, None).max() == 1.0


def test_shutter_vertices_interpolate_within_a_segment_and_mirror_at_its_ends():
    from avatarctl.synth.imperfections import shutter_offsets, shutter_vertices

    v = np.arange(5, dtype=np.float64)[:, None, None] * np.ones((1, 2, 3))  # frame k at position k
    assert np.allclose(shutter_vertices(v, 2, 0.25, (0, 5)), 2.25)
    assert np.allclose(shutter_vertices(v, 2, -0.25, (0, 5)), 1.75)
    assert np.allclose(shutter_vertices(v, 2, 0.25, (0, 3)), 2.25)  # last of its segment: mirrored, same motion
    assert np.allclose(shutter_vertices(v, 3, -0.25, (3, 5)), 2.75)  # first of the test segment: never frame 2
    assert np.allclose(shutter_vertices(v, 3, 0.1, (3, 4)), 3.0)  # a one-frame segment does not move
    off = shutter_offsets(1 / 60, 1 / 6, 5)
    assert np.allclose(off, [-0.04, -0.02, 0.0, 0.02, 0.04]) and shutter_offsets(0.0, 1 / 6, 5).tolist() == [0.0]


def test_config_validates_and_the_clean_twin_drops_every_imperfection():
    from avatarctl.errors import InputError
    from avatarctl.synth import SynthConfig
    from avatarctl.synth.config import IMPERFECTIONS

    r = SynthConfig.preset("realistic", seed=4)
    assert r.views == 4 and set(r.imperfections) >= {"exposure_ev", "white_balance", "held_out_ev", "noise_std",
                                                     "jpeg_quality", "shutter_s", "masks", "fits"}
    twin = r.clean_twin()
    assert twin.imperfections == {} and twin.seed == 4 and twin.size == r.size and twin.views == r.views
    assert all(getattr(twin, k) == v for k, v in IMPERFECTIONS.items())
    for bad in (dict(noise_std=0.5), dict(exposure_ev=-1.0), dict(shutter_s=1.0), dict(masks="mediapipe"),
                dict(fits="none", fit_noise_deg=2.0)):
        with pytest.raises(InputError, match="invalid synth config"):
            SynthConfig.preset("micro", **bad)


# ---- captures (anny) ------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def captures(tmp_path_factory):
    pytest.importorskip("anny")
    from avatarctl.synth import SynthConfig, synthesize

    root = tmp_path_factory.mktemp("realistic")
    variants = {"clean": {}, "exposure": dict(exposure_ev=0.4), "held_out": dict(held_out_ev=-0.5),
                "noise": dict(noise_std=0.03),
                "jpeg": dict(jpeg_quality=40), "blur": dict(shutter_s=0.1), "estimate": dict(masks="none", fits="none")}
    out = {}
    for name, extra in variants.items():
        out[name] = synthesize(root / name, SynthConfig.preset("micro", seed=2, **{**SMALL, **extra})).out
    return out


def _img(cap: Path, cam: str, k: int, folder: str = "images", ext: str = "jpg") -> np.ndarray:
    flag = cv2.IMREAD_COLOR if ext == "jpg" else cv2.IMREAD_UNCHANGED
    return cv2.imread(str(cap / folder / cam / f"{k:06d}.{ext}"), flag).astype(np.float64) / 255.0


def _same_files(a: Path, b: Path, pattern: str) -> None:
    fa, fb = sorted(a.glob(pattern)), sorted(b.glob(pattern))
    assert [p.relative_to(a) for p in fa] == [p.relative_to(b) for p in fb] and fa
    for p, q in zip(fa, fb):
        assert p.read_bytes() == q.read_bytes(), p.relative_to(a)


@pytest.mark.anny
def test_each_imperfection_leaves_geometry_masks_fits_and_cameras_alone(captures):
    clean = captures["clean"]
    for name in ("exposure", "held_out", "noise", "jpeg", "blur"):
        cap = captures[name]
        for f in ("gt/geometry.npz", "motion.npz", "intri.yml", "extri.yml", "split.json"):
            assert (cap / f).read_bytes() == (clean / f).read_bytes(), (name, f)
        _same_files(cap, clean, "masks/*/*.png")
        info = json.loads((cap / "capture.json").read_text())
        config, twin = info["config"], info["clean_twin"]
        assert {k for k in config if config[k] != twin[k]} == set(info["imperfections"]) and \
            len(info["imperfections"]) == 1, name
        assert any(_img(cap, "cam01", 0)[..., 0].ravel() != _img(clean, "cam01", 0)[..., 0].ravel()), name


@pytest.mark.anny
def test_exposure_scales_each_camera_by_its_recorded_gain(captures):
    clean, cap = captures["clean"], captures["exposure"]
    gains = json.loads((cap / "capture.json").read_text())["camera_colour"]
    assert json.loads((clean / "capture.json").read_text())["camera_colour"]["cam00"] == [1.0, 1.0, 1.0]
    for cam, g in gains.items():
        a, b = _img(clean, cam, 1), _img(cap, cam, 1)
        ok = (a > 0.05) & (a * max(g) < 0.95)  # not clipped, not rounded to nothing
        ratio = b[ok].sum() / a[ok].sum()
        assert abs(ratio - g[0]) < 0.02, (cam, ratio, g)  # exposure alone: the same gain in every channel
        bg_a, bg_b = (cv2.imread(str(c / "background" / f"{cam}.jpg")).astype(float) / 255 for c in (clean, cap))
        ok = (bg_a > 0.05) & (bg_a * max(g) < 0.95)
        assert abs(bg_b[ok].sum() / bg_a[ok].sum() - g[0]) < 0.02  # the plates come from the same camera
    assert np.ptp([g[0] for g in gains.values()]) > 0.1  # the cameras disagree
    held = json.loads((captures["held_out"] / "capture.json").read_text())
    split = json.loads((clean / "split.json").read_text())
    assert split["test_views"] == ["cam01"]
    assert {c: g[0] for c, g in held["camera_colour"].items()} == pytest.approx(
        {c: 2 ** -0.5 if c == "cam01" else 1.0 for c in gains})  # only the held-out camera, 0.5 stops darker
    a, b = _img(clean, "cam01", 1), _img(captures["held_out"], "cam01", 1)
    ok = a > 0.05
    assert abs(b[ok].sum() / a[ok].sum() - 2 ** -0.5) < 0.02


@pytest.mark.anny
def test_noise_has_the_set_std_and_jpeg_loses_information(captures):
    clean = captures["clean"]
    # JPEG keeps the luma at full resolution and halves the chroma: the luma of N(0, s^2) per channel has std
    # s * |(0.299, 0.587, 0.114)|; measured on it, the compression's own error on top stays within 20 %
    luma = np.array([0.114, 0.587, 0.299])  # BGR
    d = np.concatenate([((_img(captures["noise"], c, k) - _img(clean, c, k)) @ luma).ravel()
                        for c in ("cam00", "cam01") for k in range(3)])
    want = 0.03 * np.linalg.norm(luma)
    assert want < d.std() < 1.2 * want and abs(d.mean()) < 0.003
    jpg = captures["jpeg"] / "images" / "cam00" / "000000.jpg"
    assert jpg.read_bytes()[:2] == b"\xff\xd8"  # a JPEG file
    err = np.abs(_img(captures["jpeg"], "cam00", 0) - _img(clean, "cam00", 0))
    assert 1 / 255 < err.mean() < 12 / 255  # lossy, but the same picture
    assert (captures["jpeg"] / "images/cam00/000000.jpg").stat().st_size < \
        (clean / "images/cam00/000000.jpg").stat().st_size


@pytest.mark.anny
def test_motion_blur_changes_moving_edges_only(captures):
    clean, cap = captures["clean"], captures["blur"]
    k = 1
    diff = np.abs(_img(cap, "cam00", k) - _img(clean, "cam00", k)).max(-1)  # [H, W]
    near = sum(_img(clean, "cam00", j, "masks", "png") for j in (k - 1, k, k + 1)) > 0
    near = cv2.dilate(near.astype(np.uint8), np.ones((9, 9), np.uint8)) > 0
    assert diff[near].max() > 0.2  # edges smeared
    # the static background: untouched but for the JPEG blocks beside a changed edge
    assert (diff[~near] == 0).mean() > 0.5 and diff[~near].mean() < diff[near].mean() / 5


@pytest.mark.anny
def test_masks_and_fits_left_to_ingest_keep_the_truth_under_gt(captures):
    from avatarctl.io.gt_geometry import fits_are_ground_truth, masks_are_ground_truth

    clean, cap = captures["clean"], captures["estimate"]
    assert not (cap / "masks").exists() and not (cap / "motion.npz").exists()
    for f in sorted((clean / "masks").glob("*/*.png")):
        assert (cap / "gt" / "masks" / f.relative_to(clean / "masks")).read_bytes() == f.read_bytes()
    assert (cap / "gt" / "motion.npz").read_bytes() == (clean / "motion.npz").read_bytes()
    _same_files(cap, clean, "images/*/*.jpg")
    assert fits_are_ground_truth(clean) and not fits_are_ground_truth(cap)
    assert masks_are_ground_truth(clean, "files")  # the mask border decision (GaussianConfig.mask_border_px auto)
    assert not masks_are_ground_truth(clean, "mediapipe") and not masks_are_ground_truth(cap, "mediapipe")


@pytest.mark.anny
def test_the_clean_twin_of_a_realistic_capture_is_the_clean_capture(captures, tmp_path):
    from avatarctl.synth import SynthConfig, synthesize

    noisy = SynthConfig.preset("micro", seed=2, **{**SMALL, "exposure_ev": 0.3, "noise_std": 0.02})
    twin = synthesize(tmp_path / "twin", noisy.clean_twin()).out
    _same_files(twin, captures["clean"], "images/*/*.jpg")
    _same_files(twin, captures["clean"], "masks/*/*.png")


@pytest.mark.anny
def test_cli_options_reach_the_config(tmp_path):
    from typer.testing import CliRunner

    from avatarctl.cli.app import app

    out = tmp_path / "r"
    res = CliRunner().invoke(app, ["synth", str(out), "--preset", "micro", "--train-frames", "2", "--test-frames", "1",
                                   "--exposure", "0.2", "--noise", "0.01", "--jpeg-quality", "85", "--masks", "none"])
    assert res.exit_code == 0, res.output
    cfg = json.loads((out / "capture.json").read_text())["config"]
    assert (cfg["exposure_ev"], cfg["noise_std"], cfg["jpeg_quality"], cfg["masks"]) == (0.2, 0.01, 85, "none")
    assert "imperfections" in res.output and "--masks mediapipe" in res.output
    clean = tmp_path / "c"
    res = CliRunner().invoke(app, ["synth", str(clean), "--preset", "micro", "--train-frames", "2", "--test-frames",
                                   "1", "--noise", "0.01", "--clean"])
    assert res.exit_code == 0, res.output
    assert json.loads((clean / "capture.json").read_text())["imperfections"] == {}
    res = CliRunner().invoke(app, ["synth", str(tmp_path / "bad"), "--preset", "micro", "--masks", "guess"])
    assert res.exit_code == 2 and "masks must be one of" in res.output
