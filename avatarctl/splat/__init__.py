"""Differentiable 3D Gaussian splatting (Kerbl et al. 2023): world Gaussians -> image, gradients back.

Layers (gsplat's): `render_gaussians` (this file) = `project_gaussians` (project.py, pure torch: EWA projection of
mean and covariance) + `rasterize` (rasterizer.py: tile binning, then NVIDIA Warp kernels (`_warp_kernels.py`, CPU
and CUDA) behind a `torch.autograd.Function`, with a dense pure-PyTorch twin in `_torch_impl.py`). Rendering without
gradients projects with one fused kernel (`rasterizer.project_and_reach`, twin: `project_gaussians` + `reach`);
`covariance.py` gives the covariances of rotated, scaled, linearly mapped Gaussians (torch, or one kernel);
`density.py` the Gaussians as a coloured density at arbitrary points (binned Warp kernels, dense torch twin).

Conventions: metres; world->camera `x_cam = R x_world + T` (OpenCV: +z forward, x right, y down); pixel centres at
integer coordinates; colours in any number of channels C. Imports only torch, numpy, warp (lazily, on the first
Warp rasterization) and nothing of avatarctl above `geometry`.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from avatarctl.splat.camera import SplatCamera
from avatarctl.splat.project import LOW_PASS, Projected, project_gaussians, project_gaussians_batch
from avatarctl.splat.rasterizer import project_and_reach, rasterize, rasterize_batch


@dataclass
class SplatRender:
    """One rendered image."""

    rgb: torch.Tensor  # [H, W, C] composited over the background
    alpha: torch.Tensor  # [H, W] accumulated opacity
    radii: torch.Tensor  # [G] int32 screen radius, pixels; 0 = culled (not in this image)
    means2d: torch.Tensor  # [G, 2] pixels; call .retain_grad() before backward for 3DGS's densification statistic


def render_gaussians(means: torch.Tensor,  # [G, 3] world, metres
                     covars: torch.Tensor,  # [G, 3, 3] world covariance, metres^2
                     colors: torch.Tensor,  # [G, C]
                     opacities: torch.Tensor,  # [G] in [0, 1]
                     cam: SplatCamera, background: torch.Tensor,  # [C]
                     backend: str = "auto", low_pass: float = LOW_PASS) -> SplatRender:
    """Project and rasterize: the image of the Gaussians seen by `cam` (cam.width x cam.height); `low_pass` px^2
    added to every 2D covariance (project.py). Without gradients to keep (no grad mode, or no input that requires
    one) a Warp backend projects with the fused kernel (`rasterizer.project_and_reach`)."""
    grads = torch.is_grad_enabled() and any(t.requires_grad for t in (means, covars, colors, opacities))
    if backend != "torch" and not grads and means.dtype == torch.float32:
        proj = project_and_reach(means, covars, opacities, cam, low_pass=low_pass)
    else:
        proj = project_gaussians(means, covars, cam, low_pass=low_pass)
    rgb, alpha = rasterize(proj, colors, opacities, cam.width, cam.height, background, backend=backend)
    return SplatRender(rgb=rgb, alpha=alpha, radii=proj.radii, means2d=proj.means2d)


def render_gaussians_batch(means: torch.Tensor,  # [B, G, 3] world, metres: the Gaussians image b sees
                           covars: torch.Tensor,  # [B, G, 3, 3]
                           colors: torch.Tensor,  # [B, G, C]
                           opacities: torch.Tensor,  # [B, G]
                           cams: list[SplatCamera], background: torch.Tensor,  # [C]
                           backend: str = "auto", low_pass: float = LOW_PASS
                           ) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """`render_gaussians` of B images in one projection and one rasterization (`rasterize_batch`) -> [(rgb [H_b, W_b,
    C], alpha [H_b, W_b])], image b of cams[b] (each its own window size)."""
    proj = project_gaussians_batch(means, covars, cams, low_pass=low_pass)
    return rasterize_batch(proj, colors, opacities, [(c.width, c.height) for c in cams], background, backend)


__all__ = ["Projected", "SplatCamera", "SplatRender", "project_and_reach", "project_gaussians",
           "project_gaussians_batch", "rasterize", "rasterize_batch", "render_gaussians", "render_gaussians_batch"]
