"""Training losses, Eq. 11-15.

Reductions (the paper writes plain sums; ours, stated):
- L_rec (Eq. 12): the paper's sum over rays of the squared colour error (summed over channels), scaled by
  `reference_rays / R` for a batch of R rays (`ModelConfig.rec_reduction = "sum"`, reference 2048 = the
  supplement's batch). At R = 2048 this is Eq. 12 exactly; at other batch sizes it keeps the paper's balance
  between L_rec and the regularisers, which is what the lambdas were tuned for. `"mean"` (mean over rays and
  channels, = the MSE) is switchable but changes that balance by a factor 3 * 2048: with it the regularisers
  dominate, the embeddings are driven to ~0 and the cVAE posterior collapses (measured: KL ~0.1 nats over all
  nodes, i.e. the model degenerates to the no-delta-n / no-embedding ablation).
- L_trans (Eq. 13), L_ebd (Eq. 14), L_KL (Eq. 15): summed over nodes (and vector components), as in the paper,
  then averaged over the frames of the batch.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from avatarctl.model.config import REC_REDUCTIONS


@dataclass
class LossTerms:
    total: torch.Tensor  # [] Eq. 11 weighted sum
    rec: torch.Tensor  # [] Eq. 12
    trans: torch.Tensor  # [] Eq. 13
    ebd: torch.Tensor  # [] Eq. 14
    kl: torch.Tensor  # [] Eq. 15
    mse: torch.Tensor  # [] mean squared colour error over rays and channels (for logs; PSNR = -10 log10 mse)
    pose: torch.Tensor | None = None  # [] pose-refinement penalty (model/pose_refine.py), None when off
    colour: torch.Tensor | None = None  # [] the camera colour transforms' pull to identity (model/colour.py), None: off
    track: torch.Tensor | None = None  # [] Delta n's pull to the tracked garment placement (model/avatar.py), None: off
    refine: torch.Tensor | None = None  # [] the tracked placement's corrections' priors (model/track_refine.py)

    def keys(self) -> tuple[str, ...]:
        """Names of the terms this step has (the optional ones only when on; the same on every rank)."""
        return ("total", "rec", "trans", "ebd", "kl", "mse") + tuple(
            k for k in ("pose", "colour", "track", "refine") if getattr(self, k) is not None)

    def as_floats(self) -> dict[str, float]:
        return {k: float(getattr(self, k).detach()) for k in self.keys()}


def reconstruction_loss(rgb: torch.Tensor, target: torch.Tensor, reduction: str = "sum",
                        reference_rays: int = 2048) -> torch.Tensor:
    """Eq. 12: [rays, 3], [rays, 3] -> sum_r ||C_r - C^_r||^2 * reference_rays / rays ("sum"), or the mean
    squared error over rays and channels ("mean"); see the module docstring."""
    assert rgb.shape == target.shape, f"rendered {tuple(rgb.shape)} vs target {tuple(target.shape)}"
    se = (rgb - target.to(rgb.dtype)) ** 2
    if reduction == "mean":
        return se.mean()
    if reduction == "sum":
        return se.sum() * (reference_rays / max(rgb.shape[0], 1))
    raise ValueError(f"unknown reconstruction reduction {reduction!r}; use one of {REC_REDUCTIONS}")


def translation_loss(delta_n: torch.Tensor) -> torch.Tensor:
    """Eq. 13: sum_i ||Delta n_i||^2, [frames, N, 3] -> mean over frames."""
    return (delta_n ** 2).sum(dim=(-2, -1)).mean()


def embedding_loss(embed: torch.Tensor) -> torch.Tensor:
    """Eq. 14: sum_i ||e_i||^2, [frames, N, E] -> mean over frames."""
    return (embed ** 2).sum(dim=(-2, -1)).mean()


def kl_loss(mu: torch.Tensor, logvar: torch.Tensor) -> torch.Tensor:
    """Eq. 15: sum_i KL(N(mu_i, sigma_i^2) || N(0, I)), [frames, N, Z] -> mean over frames.

    KL = 0.5 * sum_z (mu^2 + sigma^2 - log sigma^2 - 1)."""
    return (0.5 * (mu ** 2 + torch.exp(logvar) - logvar - 1.0)).sum(dim=(-2, -1)).mean()


def total_loss(rec: torch.Tensor, trans: torch.Tensor, ebd: torch.Tensor, kl: torch.Tensor, lambda_rec: float,
               lambda_trans: float, lambda_ebd: float, lambda_kl: float, mse: torch.Tensor,
               pose: torch.Tensor | None = None, lambda_pose: float = 0.0,
               colour: torch.Tensor | None = None, lambda_colour: float = 0.0,
               track: torch.Tensor | None = None, lambda_track: float = 0.0,
               refine: torch.Tensor | None = None) -> LossTerms:
    """Eq. 11: L = lambda_rec L_rec + lambda_trans L_trans + lambda_ebd L_ebd + lambda_KL L_KL, plus
    lambda_pose L_pose when pose refinement is on (a deviation,
    model/pose_refine.py), plus lambda_colour L_colour when the camera colour transforms are on (a deviation,
    model/colour.py), plus lambda_track L_track when garment tracks place nodes (a deviation, model/avatar.py) and
    L_refine, weighted already, when their placement is corrected per frame (model/track_refine.py). `mse`
    (the mean squared colour error) is carried along for the logs only."""
    total = lambda_rec * rec + lambda_trans * trans + lambda_ebd * ebd + lambda_kl * kl
    if pose is not None:
        total = total + lambda_pose * pose
    if colour is not None:
        total = total + lambda_colour * colour
    if track is not None:
        total = total + lambda_track * track
    if refine is not None:
        total = total + refine
    return LossTerms(total=total, rec=rec, trans=trans, ebd=ebd, kl=kl, mse=mse, pose=pose, colour=colour,
                     track=track, refine=refine)


def _gaussian_window(size: int = 11, sigma: float = 1.5, device=None, dtype=None) -> torch.Tensor:
    x = torch.arange(size, device=device, dtype=dtype) - (size - 1) / 2
    g = torch.exp(-x * x / (2 * sigma * sigma))
    return g / g.sum()


def ssim_map(a: torch.Tensor, b: torch.Tensor, window: int = 11) -> torch.Tensor:
    """Differentiable SSIM (Wang et al. 2004; Gaussian window 11, sigma 1.5, C1 = 0.01^2, C2 = 0.03^2; the
    image's own borders zero-padded as 3DGS trains it): images [H, W, C] in [0, 1] -> [H, W, C] SSIM map. A training
    loss only; scores are computed by evaluate/metrics.py."""
    C = a.shape[-1]
    x = torch.stack([a, b, a * a, b * b, a * b]).permute(0, 3, 1, 2).reshape(1, 5 * C, *a.shape[:2])
    g = _gaussian_window(window, 1.5, a.device, a.dtype)
    x = torch.nn.functional.conv2d(x, g.reshape(1, 1, 1, -1).expand(5 * C, 1, 1, window), padding=(0, window // 2),
                                   groups=5 * C)
    x = torch.nn.functional.conv2d(x, g.reshape(1, 1, -1, 1).expand(5 * C, 1, window, 1), padding=(window // 2, 0),
                                   groups=5 * C)
    mu_a, mu_b, aa, bb, ab = x.reshape(5, C, *a.shape[:2]).permute(0, 2, 3, 1).unbind(0)
    va, vb, cov = aa - mu_a * mu_a, bb - mu_b * mu_b, ab - mu_a * mu_b
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    return ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a * mu_a + mu_b * mu_b + c1) * (va + vb + c2))


def mask_border_weight(mask: torch.Tensor, border_px: int) -> torch.Tensor:
    """0 within `border_px` pixels either side of `mask`'s outline (mask [h, w], thresholded at 0.5), 1 elsewhere:
    the pixels an estimated mask's wrong outline mislabels, left out of the image loss as Neural Body leaves out its
    masks' border (`GaussianConfig.mask_border_px`; the band: `geometry.silhouette.outline_band`). The crop's own
    edge is no outline. -> [h, w] float32"""
    from avatarctl.geometry.silhouette import outline_band

    return 1 - outline_band(mask, border_px).to(torch.float32)


def image_reconstruction_loss(rgb: list[torch.Tensor], target: list[torch.Tensor], alpha: list[torch.Tensor],
                              mask: list[torch.Tensor], lambda_ssim: float, lambda_mask: float,
                              reference_rays: int = 2048, border_px: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """L_rec of the rasterized (Gaussian) field, trained on whole image crops (3DGS's loss, a deviation from Eq. 12):
    per image (1 - lambda_ssim) L1 + lambda_ssim (1 - SSIM) over pixels, summed over channels, plus lambda_mask
    |alpha - mask| per pixel; averaged over the images and scaled by `reference_rays`, so that it weighs against
    the regularisers of Eq. 11 as Eq. 12's sum over the paper's 2048 rays does. rgb / target [h, w, 3], alpha / mask
    [h, w] per image (images of different sizes). `border_px` > 0: the L1, the SSIM map and the mask term weighted by
    `mask_border_weight` (the outline's pixels out; the SSIM windows of the pixels beside them still read them), each
    a mean over the pixels left in. -> (loss, mean squared colour error for the logs)."""
    terms, se, n = [], 0.0, 0
    for c, t, a, m in zip(rgb, target, alpha, mask, strict=True):
        t = t.to(c.dtype)
        l1, dssim, mask_err = (c - t).abs(), 1 - ssim_map(c, t), (a - m.to(a.dtype)).abs()
        if border_px > 0:
            w = mask_border_weight(m, border_px).to(c.dtype)
            share = w.mean().clamp_min(1e-6)
            l1, dssim, mask_err = l1 * w[..., None] / share, dssim * w[..., None] / share, mask_err * w / share
        photo = (1 - lambda_ssim) * l1.mean() + lambda_ssim * dssim.mean()
        terms.append(3 * photo + lambda_mask * mask_err.mean())
        se = se + ((c.detach() - t) ** 2).sum()
        n += c.numel()
    return torch.stack(terms).mean() * reference_rays, se / max(n, 1)
