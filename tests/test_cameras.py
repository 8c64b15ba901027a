"""Camera projection against OpenCV, resizing, look-at, EasyMocap calibration files."""

from __future__ import annotations

import numpy as np
import pytest

from avatarctl.errors import InputError
from avatarctl.io.easymocap import read_easymocap_cameras, write_easymocap_cameras
from avatarctl.geometry.cameras import Camera, look_at


def _cam(dist=(0.12, -0.05, 0.001, -0.002, 0.01)):
    R, T = look_at(np.array([2.5, -1.0, 1.2]), np.array([0.0, 0.0, 0.1]))
    K = np.array([[210.0, 0, 95.5], [0, 205.0, 80.2], [0, 0, 1]])
    return Camera("cam00", K, R, T, 192, 160, np.array(dist))


def test_project_matches_cv2_projectpoints_with_distortion():
    import cv2

    cam = _cam()
    X = np.random.default_rng(0).uniform(-0.5, 0.5, size=(200, 3))
    ours = cam.project(X)
    ref, _ = cv2.projectPoints(X, cv2.Rodrigues(cam.R)[0], cam.T, cam.K, cam.dist)
    np.testing.assert_allclose(ours, ref.reshape(-1, 2), atol=1e-6)


def test_look_at_points_camera_at_target():
    cam = _cam(dist=(0, 0, 0, 0, 0))
    uv = cam.project(np.array([[0.0, 0.0, 0.1]]))[0]
    np.testing.assert_allclose(uv, cam.K[:2, 2], atol=1e-9)
    np.testing.assert_allclose(cam.center, [2.5, -1.0, 1.2], atol=1e-12)
    # world up (+z) appears upward in the image (smaller y)
    above = cam.project(np.array([[0.0, 0.0, 0.6]]))[0]
    assert above[1] < uv[1]


def test_scaled_camera_matches_resized_pixel_grid():
    cam = _cam(dist=(0, 0, 0, 0, 0))
    half = cam.scaled(0.5)
    X = np.random.default_rng(1).uniform(-0.3, 0.3, size=(20, 3))
    # pixel-centre convention: u' = (u + 0.5) * s - 0.5
    np.testing.assert_allclose(half.project(X), (cam.project(X) + 0.5) * 0.5 - 0.5, atol=1e-9)
    assert (half.width, half.height) == (96, 80)


def test_easymocap_roundtrip(tmp_path):
    cams = [_cam(), Camera("cam01", np.eye(3) * 100 + np.diag([0, 0, -99]), np.eye(3), [0, 0, 3.0], 64, 48)]
    write_easymocap_cameras(tmp_path, cams)
    back = read_easymocap_cameras(tmp_path)
    assert [c.name for c in back] == ["cam00", "cam01"]
    for a, b in zip(cams, back):
        np.testing.assert_allclose(a.K, b.K)
        np.testing.assert_allclose(a.R, b.R, atol=1e-12)
        np.testing.assert_allclose(a.T, b.T)
        np.testing.assert_allclose(a.dist, b.dist)
        assert (a.width, a.height) == (b.width, b.height)


def test_easymocap_missing_file_and_missing_camera(tmp_path):
    with pytest.raises(InputError, match="missing calibration file intri.yml"):
        read_easymocap_cameras(tmp_path)
    write_easymocap_cameras(tmp_path, [_cam()])
    text = (tmp_path / "extri.yml").read_text().replace("cam00", "camXX")
    (tmp_path / "extri.yml").write_text(text)
    with pytest.raises(InputError, match=r"\['cam00'\] are in intri.yml but not in extri.yml"):
        read_easymocap_cameras(tmp_path)
