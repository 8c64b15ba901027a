"""The one metrics module (`avatarctl.evaluate.metrics`) against hand-computed PSNR / SSIM on known images."""

from __future__ import annotations

import math

import numpy as np
import pytest

from avatarctl.evaluate import metrics


def test_psnr_constant_error_is_20_db():
    gt = np.zeros((8, 9, 3), np.float32)
    pred = np.full_like(gt, 0.1)  # MSE = 0.01 -> PSNR = -10 log10(0.01) = 20 dB
    assert metrics.psnr(pred, gt) == pytest.approx(20.0, abs=1e-4)


def test_psnr_uint8_full_scale_is_0_db_and_identical_is_inf():
    a = np.zeros((4, 4, 3), np.uint8)
    b = np.full((4, 4, 3), 255, np.uint8)
    assert metrics.psnr(a, b) == pytest.approx(0.0, abs=1e-6)  # uint8 / 255 -> MSE 1
    assert math.isinf(metrics.psnr(b, b))


def test_psnr_counts_only_mask_pixels():
    gt = np.zeros((10, 10, 3), np.float32)
    pred = gt.copy()
    pred[:, 5:] = 1.0  # right half wrong by 1.0
    pred[2:4, 1:3] = 0.5  # a 2x2 patch wrong by 0.5 in the left half
    mask = np.zeros((10, 10), bool)
    mask[:, :5] = True  # left half only: 4 of 50 pixels err by 0.5 -> MSE = 4 * 0.25 / 50 = 0.02
    assert metrics.mse(pred, gt, mask) == pytest.approx(0.02, rel=1e-6)
    assert metrics.psnr(pred, gt, mask) == pytest.approx(-10 * math.log10(0.02), abs=1e-4)
    # whole image: (50 * 1 + 4 * 0.25) / 100 = 0.51
    assert metrics.psnr(pred, gt) == pytest.approx(-10 * math.log10(0.51), abs=1e-4)
    with pytest.raises(ValueError, match="empty"):
        metrics.psnr(pred, gt, np.zeros((10, 10), bool))


def test_ssim_identical_is_one():
    rng = np.random.default_rng(0)
    img = rng.random((20, 24, 3), dtype=np.float32)
    assert metrics.ssim(img, img) == pytest.approx(1.0, abs=1e-6)


def test_ssim_of_constant_images_matches_the_formula():
    # constant images: variances and covariance are 0, so SSIM = (2 a b + C1) / (a^2 + b^2 + C1), C1 = (0.01 * 1)^2
    a, b = 0.5, 0.25
    pred = np.full((16, 16, 3), a, np.float32)
    gt = np.full((16, 16, 3), b, np.float32)
    c1 = (0.01 * 1.0) ** 2
    expected = (2 * a * b + c1) / (a * a + b * b + c1)
    assert metrics.ssim(pred, gt) == pytest.approx(expected, abs=1e-5)


def _ssim_by_hand(x: np.ndarray, y: np.ndarray, win: int = 7) -> float:
    """Wang et al. 2004 SSIM with a win x win uniform window, sample covariance, data range 1, border of
    (win - 1) / 2 pixels dropped, mean over pixels then channels: the settings the metrics module records."""
    from scipy.ndimage import uniform_filter

    c1, c2 = (0.01 * 1.0) ** 2, (0.03 * 1.0) ** 2
    n = win * win
    cov_norm = n / (n - 1)
    pad = (win - 1) // 2
    vals = []
    for c in range(x.shape[2]):
        a, b = x[..., c].astype(np.float64), y[..., c].astype(np.float64)
        ux, uy = uniform_filter(a, win), uniform_filter(b, win)
        vx = cov_norm * (uniform_filter(a * a, win) - ux * ux)
        vy = cov_norm * (uniform_filter(b * b, win) - uy * uy)
        vxy = cov_norm * (uniform_filter(a * b, win) - ux * uy)
        s = ((2 * ux * uy + c1) * (2 * vxy + c2)) / ((ux * ux + uy * uy + c1) * (vx + vy + c2))
        vals.append(s[pad:-pad, pad:-pad].mean())
    return float(np.mean(vals))


def test_ssim_matches_a_hand_computation_on_random_images():
    rng = np.random.default_rng(1)
    gt = rng.random((23, 31, 3)).astype(np.float32)
    pred = np.clip(gt + rng.normal(0, 0.1, gt.shape), 0, 1).astype(np.float32)
    assert metrics.ssim(pred, gt) == pytest.approx(_ssim_by_hand(pred, gt), abs=1e-4)


def test_ssim_rejects_images_smaller_than_the_window():
    with pytest.raises(ValueError, match="window"):
        metrics.ssim(np.zeros((5, 40, 3), np.float32), np.zeros((5, 40, 3), np.float32))


def test_settings_record_library_version_and_window():
    import skimage

    s = metrics.metric_settings()
    assert s["scikit_image"] == skimage.__version__
    assert s["ssim"]["win_size"] == 7 and s["ssim"]["data_range"] == 1.0 and s["ssim"]["gaussian_weights"] is False
