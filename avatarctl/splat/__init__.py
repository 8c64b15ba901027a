"""Differentiable 3D Gaussian splatting (Kerbl et al. 2023): world Gaussians -> images, gradients back.

The library's face is one batch-first entry point, `rasterization` (rendering.py; gsplat's): B cameras, one image
each (one image is the batch of one) -> (rgb, alpha, `SplatMeta`: radii, 2D means, depths). Its layers (gsplat's):
`project.project_gaussians` (pure torch: EWA projection of mean and covariance) + `rasterizer.rasterize` (the B images
on one canvas, tile binning, then NVIDIA Warp kernels (`_warp_kernels.py`, CPU and CUDA) behind a
`torch.autograd.Function` whose backward computes only the gradients required, with a dense pure-PyTorch twin in
`_torch_impl.py`). Rendering without gradients projects with one fused kernel (`rasterizer.project_and_reach`, twin:
`project_gaussians` + `rasterizer.reach`); `covariance.py` gives the covariances of rotated, scaled, linearly mapped
Gaussians (torch, or one kernel); `density.py` the Gaussians as a coloured density at arbitrary points (binned Warp
kernels, dense torch twin). The layers' modules are imported by the tests and benchmarks that check or time one
layer; callers use `rasterization`.

Conventions: metres; world->camera `x_cam = R x_world + T` (OpenCV: +z forward, x right, y down); pixel centres at
integer coordinates; colours in any number of channels C. Imports only torch, numpy, warp (lazily, on the first
Warp rasterization) and nothing of avatarctl above `geometry`.
"""

from __future__ import annotations

from avatarctl.splat.camera import SplatCamera
from avatarctl.splat.project import LOW_PASS
from avatarctl.splat.rendering import SplatMeta, rasterization

__all__ = ["LOW_PASS", "SplatCamera", "SplatMeta", "rasterization"]
