"""Evaluation protocols: the `bbox` region against a hand-built mask, `full`, and scoring inside the region."""

from __future__ import annotations

import math

import numpy as np
import pytest

from avatarctl.evaluate import metrics
from avatarctl.evaluate.protocols import bbox_region, box_corners, full_region
from avatarctl.geometry.cameras import Camera


def _camera() -> Camera:
    # looks down +z from the origin; f = 100 px, principal point (50, 40), 100 x 80 image
    K = np.array([[100.0, 0, 50.0], [0, 100.0, 40.0], [0, 0, 1]])
    return Camera(name="c", K=K, R=np.eye(3), T=np.zeros(3), width=100, height=80)


def _box_vertices() -> np.ndarray:
    """Points filling the box x in [-0.2, 0.2], y in [-0.3, 0.3], z in [2, 4] (corners included)."""
    rng = np.random.default_rng(0)
    lo, hi = np.array([-0.2, -0.3, 2.0]), np.array([0.2, 0.3, 4.0])
    pts = lo + rng.random((200, 3)) * (hi - lo)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    return np.concatenate([pts, corners])


def test_bbox_region_matches_hand_built_mask():
    # with no padding the near face (z = 2) projects to u = 50 +- 10, v = 40 +- 15 and hides the far face, so the
    # convex hull of the 8 projected corners is exactly the pixel rectangle u 40..60, v 25..55 (boundary included)
    region = bbox_region(_camera(), _box_vertices(), pad=0.0)
    hand = np.zeros((80, 100), bool)
    hand[25:56, 40:61] = True
    assert region.mask.shape == (80, 100)
    assert np.array_equal(region.mask, hand), f"{region.mask.sum()} vs {hand.sum()} pixels"
    assert region.crop == (40, 25, 61, 56)
    img = np.arange(80 * 100 * 3, dtype=np.float32).reshape(80, 100, 3)
    assert region.crop_image(img).shape == (31, 21, 3)


def test_bbox_padding_grows_the_region():
    cam = _camera()
    tight = bbox_region(cam, _box_vertices(), pad=0.0)
    padded = bbox_region(cam, _box_vertices(), pad=0.1)
    assert (padded.mask | tight.mask).sum() == padded.mask.sum()  # tight is inside padded
    assert padded.mask.sum() > tight.mask.sum() * 1.3
    corners = box_corners(_box_vertices(), pad=0.1)
    assert corners.shape == (8, 3) and np.allclose(corners.min(0), [-0.3, -0.4, 1.9])


def test_full_region_is_every_pixel():
    r = full_region(7, 9)
    assert r.mask.shape == (7, 9) and r.mask.all() and r.crop == (0, 0, 9, 7)


def test_psnr_in_bbox_ignores_errors_outside_and_matches_hand_value():
    region = bbox_region(_camera(), _box_vertices(), pad=0.0)
    gt = np.zeros((80, 100, 3), np.float32)
    pred = gt.copy()
    pred[~region.mask] = 1.0  # large error outside the box: not counted
    assert math.isinf(metrics.psnr(pred, gt, region.mask))
    pred[30:40, 45:55] += 0.2  # 100 pixels inside the box off by 0.2
    n = region.mask.sum()
    expected = -10 * math.log10(100 * 0.04 / n)
    assert metrics.psnr(pred, gt, region.mask) == pytest.approx(expected, abs=1e-3)
