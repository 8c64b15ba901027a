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
    pose_accel: torch.Tensor | None = None  # [] acceleration of the refined poses (model/pose_refine.py), None: off

    def keys(self) -> tuple[str, ...]:
        """Names of the terms this step has (the optional ones only when on; the same on every rank)."""
        return ("total", "rec", "trans", "ebd", "kl", "mse") + tuple(
            k for k in ("pose", "pose_accel") if getattr(self, k) is not None)

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
               pose_accel: torch.Tensor | None = None, lambda_pose_accel: float = 0.0) -> LossTerms:
    """Eq. 11: L = lambda_rec L_rec + lambda_trans L_trans + lambda_ebd L_ebd + lambda_KL L_KL, plus
    lambda_pose L_pose (+ lambda_pose_accel L_accel) when pose refinement is on (a deviation,
    model/pose_refine.py). `mse` (the mean squared colour error) is carried along for the logs only."""
    total = lambda_rec * rec + lambda_trans * trans + lambda_ebd * ebd + lambda_kl * kl
    if pose is not None:
        total = total + lambda_pose * pose
    if pose_accel is not None:
        total = total + lambda_pose_accel * pose_accel
    return LossTerms(total=total, rec=rec, trans=trans, ebd=ebd, kl=kl, mse=mse, pose=pose, pose_accel=pose_accel)
