"""Orbit cameras, MP4 writing, frame/background option parsing and the comparison sheet (no avatar needed)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from avatarctl.errors import InputError
from avatarctl.geometry.cameras import Camera, look_at
from avatarctl.render.trajectories import OrbitSpec, orbit_cameras, orbit_defaults, smooth_centers, up_from_cameras


def _ring(n=4, up=np.array([0.0, 0.0, 1.0])):
    cams = []
    K = np.array([[50.0, 0, 31.5], [0, 50.0, 31.5], [0, 0, 1]])
    for i in range(n):
        a = 2 * np.pi * i / n
        eye = np.array([3 * np.cos(a), 3 * np.sin(a), 0.5])
        R, T = look_at(eye, np.zeros(3), up=up)
        cams.append(Camera(name=f"c{i}", K=K, R=R, T=T, width=64, height=64))
    return cams


def test_up_from_upright_cameras():
    assert np.allclose(up_from_cameras(_ring()), [0, 0, 1], atol=0.05)
    assert np.allclose(up_from_cameras(_ring(up=np.array([0.0, -1.0, 0.0]))), [0, -1, 0], atol=0.05)


def test_orbit_geometry():
    n, radius, elev, extent = 8, 3.0, 20.0, 0.9
    center = np.array([0.3, -0.2, 0.1])
    spec = OrbitSpec(views=n, elevation_deg=elev, radius=radius, resolution=96)
    cams = orbit_cameras(spec, np.repeat(center[None], n, 0), extent, np.array([0, 0, 1.0]), radius,
                         reference_dir=np.array([0, -1.0, 0]))
    assert len(cams) == n and all(c.width == 96 and c.height == 96 for c in cams)
    azimuths = []
    for c in cams:
        off = c.center - center
        assert np.linalg.norm(off) == pytest.approx(radius, abs=1e-9)
        assert math.degrees(math.asin(off[2] / radius)) == pytest.approx(elev, abs=1e-6)
        assert np.allclose(c.project(center[None])[0], [47.5, 47.5], atol=1e-6)  # looks at the centre
        assert np.allclose(np.linalg.det(c.R), 1.0) and c.R[1] @ np.array([0, 0, 1.0]) < 0  # upright: image y down
        azimuths.append(math.atan2(off[1], off[0]))
    steps = np.diff(np.unwrap(azimuths))
    assert np.allclose(np.abs(steps), 2 * np.pi / n, atol=1e-9) and (np.all(steps > 0) or np.all(steps < 0))
    assert np.allclose((cams[0].center - center)[:2] / np.linalg.norm((cams[0].center - center)[:2]), [0, -1])
    # a sphere of radius `extent` around the centre stays inside the image (fill 0.9)
    rng = np.random.default_rng(0)
    d = rng.normal(size=(500, 3))
    pts = center + extent * d / np.linalg.norm(d, axis=1, keepdims=True)
    for c in cams:
        uv = c.project(pts)
        assert uv.min() > 0 and uv.max() < 95


def test_orbit_defaults_and_smoothing():
    cams = _ring()
    dist, elev, ref = orbit_defaults(cams, np.zeros(3), np.array([0, 0, 1.0]))
    assert dist == pytest.approx(math.sqrt(9 + 0.25)) and elev == pytest.approx(math.degrees(math.atan2(0.5, 3)))
    assert abs(ref[2]) < 1e-12
    c = np.zeros((20, 3))
    c[10:] = 1.0
    s = smooth_centers(c, window=5)
    assert s.shape == (20, 3) and np.allclose(s[:8], 0) and np.allclose(s[12:], 1) and 0 < s[10, 0] < 1
    with pytest.raises(ValueError, match="inside the subject"):
        orbit_cameras(OrbitSpec(views=1), np.zeros((1, 3)), 1.0, np.array([0, 0, 1.0]), 0.5)


def test_video_is_h264_yuv420p_with_even_size(tmp_path):
    from avatarctl.render.video import probe_video, tile, write_video

    frames = [np.full((33, 21, 3), 40 * i, np.uint8) for i in range(6)]  # odd size: padded, not rescaled
    info = write_video(frames, tmp_path / "v.mp4", fps=12)
    assert (info.width, info.height, info.frames) == (22, 34, 6)
    meta = probe_video(tmp_path / "v.mp4")
    assert meta["codec"] == "h264" and meta["pix_fmt"] == "yuv420p" and meta["size"] == (22, 34)
    assert meta["frames"] == 6 and meta["fps"] == pytest.approx(12)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["v.mp4"]  # no temporary left behind
    grid = tile([np.zeros((4, 5, 3), np.uint8), np.full((3, 5, 3), 9, np.uint8)], columns=2)
    assert grid.shape == (4, 10, 3) and grid[0, 5, 0] == 9
    with pytest.raises(ValueError, match="no frames"):
        write_video([], tmp_path / "empty.mp4", fps=10)
    assert not (tmp_path / "empty.mp4").exists()


def test_frame_selection_spec():
    from avatarctl.frames import select_frames

    avail = [0, 2, 4, 6, 8, 10]
    assert select_frames(None, avail) == avail
    assert select_frames("2:9", avail) == [2, 4, 6, 8]
    assert select_frames("0:11:4", avail) == [0, 4, 8]
    assert select_frames(":5", avail) == [0, 2, 4]
    assert select_frames("10,2", avail) == [2, 10]
    assert select_frames("test", avail, train=[0, 2], test=[8, 10]) == [8, 10]
    for bad, match in (("3", "not available"), ("a:b", "cannot parse"), ("1:2", "selects no frame"),
                       ("0:9:0", "cannot parse"), ("train", "only applies")):
        with pytest.raises(InputError, match=match):
            select_frames(bad, avail)


def test_background_spec():
    from avatarctl.stages.render import RenderConfig, parse_background

    assert parse_background("fit", (0.2, 0.3, 0.4)) == ((0.2, 0.3, 0.4), False)
    assert parse_background("white", (0, 0, 0)) == ((1.0, 1.0, 1.0), False)
    assert parse_background("transparent", (1, 1, 1)) == ((0.0, 0.0, 0.0), True)
    assert parse_background("255,0,51", (0, 0, 0))[0] == pytest.approx((1.0, 0.0, 0.2))
    with pytest.raises(InputError, match="background"):
        parse_background("pink", (0, 0, 0))
    with pytest.raises(InputError, match="exclusive"):
        RenderConfig(views=("a",), orbit=3)
    with pytest.raises(InputError, match="latent"):
        RenderConfig(latent="posterior")
    with pytest.raises(Exception, match="invalid render name"):
        RenderConfig(name="../x")


def test_comparison_sheet_layout(tmp_path):
    import cv2

    from avatarctl.evaluate.sheet import SheetRow, comparison_sheet, error_map

    gt = np.zeros((20, 10, 3), np.float32)
    pred = gt.copy()
    pred[5:10] = 1.0
    em = error_map(pred, gt, max_error=0.25)
    assert em.shape == (20, 10, 3) and em[0].max() < 10 and em[7].min() > 100  # black where right, bright where wrong
    rows = [SheetRow(gt=gt, render=pred, region=None, label="frame 0  view c  PSNR 6.02 dB")] * 2
    out = comparison_sheet(rows, tmp_path / "sheet.png", title="test")
    img = cv2.imread(str(out))
    assert img is not None and img.shape[0] >= 2 * 200 and img.shape[1] >= 3 * 10 * 10
