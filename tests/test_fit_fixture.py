"""A check that the tiny project fixture (`tests/fixtures/tiny_project.py`) is sane."""

from __future__ import annotations

import pytest
from fixtures.tiny_project import make_tiny_project


@pytest.mark.anny
def test_tiny_project_images_show_the_body(tmp_path):
    from avatarctl.io.project_io import load_project_capture

    cap = load_project_capture(make_tiny_project(tmp_path / "p", size=32, frames=1, cams=2))
    for cam in cap.cameras:
        img, mask = cap.image(cam, 0), cap.mask(cam, 0)
        assert img.shape == (32, 32, 3) and mask.shape == (32, 32)
        assert 0.05 < mask.mean() < 0.6, f"{cam}: body covers {mask.mean():.2f} of the image"
        assert img[~mask].mean() < 5 and img[mask].mean() > 40  # black outside (JPEG ringing aside), painted inside
