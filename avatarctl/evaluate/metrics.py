"""The one metrics module: PSNR and SSIM (and LPIPS when installed), used by fit-time validation and `avatarctl eval`.

All scores are computed in float32 on images with values in [0, 1] (uint8 inputs are divided by 255).
SSIM is scikit-image's `structural_similarity` with the settings in `SSIM_SETTINGS` (recorded beside every number,
with the scikit-image version, because SSIM values differ between versions and settings).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

# Neural Body's evaluation calls skimage SSIM on the box crop with channel_axis and data_range=1 (float images);
# we use the same defaults: 7x7 uniform window, no Gaussian weighting.
SSIM_SETTINGS: dict[str, Any] = {"data_range": 1.0, "channel_axis": -1, "win_size": 7, "gaussian_weights": False}


def to_float(img: np.ndarray) -> np.ndarray:
    """uint8 or float image -> float32 in [0, 1]."""
    a = np.asarray(img)
    if a.dtype == np.uint8:
        return a.astype(np.float32) / 255.0
    return a.astype(np.float32)


def _squared_errors(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
    """(pred - gt)^2 [H, W, C], or [n, C] over the `mask` pixels ([H, W] bool) when given."""
    p, g = to_float(pred), to_float(gt)
    assert p.shape == g.shape, f"pred {p.shape} vs gt {g.shape}"
    d = (p - g) ** 2
    if mask is not None:
        m = np.asarray(mask, dtype=bool)
        assert m.shape == p.shape[:2], f"mask {m.shape} vs image {p.shape[:2]}"
        if not m.any():
            raise ValueError("empty evaluation mask")
        d = d[m]
    return d


def mse(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean squared error over pixels (and channels); over `mask` pixels only when given ([H, W] bool)."""
    return float(_squared_errors(pred, gt, mask).mean(dtype=np.float64))


def mse_channels(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """[C] the mean squared error of each channel over the pixels (over `mask` pixels when given); `mse` is their
    mean. A camera g_k times brighter in channel k scales that channel's error by g_k^2."""
    d = _squared_errors(pred, gt, mask)
    return d.reshape(-1, d.shape[-1]).mean(0, dtype=np.float64)


def psnr_from_mse(m: float) -> float:
    return float("inf") if m <= 0 else float(-10.0 * np.log10(m))


def psnr(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> float:
    """PSNR in dB for images in [0, 1]: -10 log10(MSE), over `mask` pixels when given."""
    return psnr_from_mse(mse(pred, gt, mask))


def ssim(pred: np.ndarray, gt: np.ndarray) -> float:
    """SSIM of two [H, W, 3] images in [0, 1] with `SSIM_SETTINGS` (crop to the box first for the bbox protocol)."""
    from skimage.metrics import structural_similarity

    p, g = to_float(pred), to_float(gt)
    assert p.shape == g.shape, f"pred {p.shape} vs gt {g.shape}"
    win = SSIM_SETTINGS["win_size"]
    if min(p.shape[:2]) < win:
        raise ValueError(f"image {p.shape[:2]} smaller than the SSIM window {win}")
    return float(structural_similarity(p, g, **SSIM_SETTINGS))


def metric_settings() -> dict[str, Any]:
    """What to record beside every number."""
    import skimage

    return {"psnr": "-10*log10(MSE), images in [0,1], float32", "ssim": dict(SSIM_SETTINGS),
            "scikit_image": skimage.__version__}


def lpips_status() -> tuple[Any | None, str]:
    """(an LPIPS function or None, reason). Never downloads: the weights must already be on this machine."""
    import importlib.util

    if importlib.util.find_spec("lpips") is None:
        return None, "lpips package not installed (pip install lpips, with its AlexNet weights cached locally)"
    try:
        import torch

        hub = Path(torch.hub.get_dir()) / "checkpoints"
        alex = sorted(hub.glob("alexnet-owt-*.pth"))
        if not alex:
            return None, f"AlexNet backbone weights not found in {hub} (LPIPS would download them; we never do)"
        import lpips  # type: ignore[import-not-found]

        net = lpips.LPIPS(net="alex", verbose=False).eval()

        def score(pred: np.ndarray, gt: np.ndarray) -> float:
            p = torch.from_numpy(np.ascontiguousarray(pred, dtype=np.float32)).permute(2, 0, 1)[None] * 2 - 1
            g = torch.from_numpy(np.ascontiguousarray(gt, dtype=np.float32)).permute(2, 0, 1)[None] * 2 - 1
            with torch.no_grad():
                return float(net(p, g).item())

        return score, f"lpips {getattr(lpips, '__version__', '?')} (alex), inputs scaled to [-1, 1]"
    except Exception as e:  # noqa: BLE001 - any failure means LPIPS is unavailable, said plainly
        return None, f"lpips unavailable ({type(e).__name__}: {e})"
