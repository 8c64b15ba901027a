"""`rasterization`: the library's one entry point, world Gaussians seen by B cameras -> B images (gsplat's
`rasterization`, our layers): `project.project_gaussians` (EWA projection in torch, autograd) or, where no gradient
is required, `rasterizer.project_and_reach` (one fused Warp kernel per camera), then `rasterizer.rasterize` (the B
images on one canvas, binned and composited once).

Shapes, batch first: B = len(cams) images, G Gaussians each, C colour channels. Each of means, covars, colors and
opacities comes with its leading [B] (image b's own Gaussians: frame b of an animated avatar, camera-dependent
colours) or without it (the same for every image, as gsplat's cameras share one scene); one image is the batch of
one. The images come back as one tensor [B, H, W, C] when every camera has one size, a list of [H_b, W_b, C] when
sizes differ (crops of several sizes, as training takes them): `rgb[b]` is image b either way, and a list cannot
pad images to a common size nobody asked for.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch

from avatarctl.splat.camera import SplatCamera
from avatarctl.splat.project import LOW_PASS, project_gaussians
from avatarctl.splat.rasterizer import project_and_reach, rasterize


@dataclass(frozen=True)
class SplatMeta:
    """What a caller may need besides the images, one row per (image, Gaussian)."""

    radii: torch.Tensor  # [B, G] int32 screen radius, pixels; 0 = culled (not in image b)
    # [B, G, 2] pixels, the rasterizer's input (a non-leaf of the graph where gradients are computed): call
    # .retain_grad() on it before backward for 3DGS's densification statistic |dL/dmean2d|
    means2d: torch.Tensor
    depths: torch.Tensor  # [B, G] camera z, metres (the compositing order)


def rasterization(means: torch.Tensor,  # [B, G, 3] or [G, 3] world, metres
                  covars: torch.Tensor,  # [B, G, 3, 3] or [G, 3, 3] world covariance, metres^2
                  colors: torch.Tensor,  # [B, G, C] or [G, C]
                  opacities: torch.Tensor,  # [B, G] or [G] in [0, 1]
                  cams: Sequence[SplatCamera],  # [B], each its own window size
                  background: torch.Tensor,  # [C]
                  backend: str = "auto", low_pass: float = LOW_PASS
                  ) -> tuple[torch.Tensor | list[torch.Tensor], torch.Tensor | list[torch.Tensor], SplatMeta]:
    """The images of the Gaussians seen by `cams` over `background` -> (rgb, alpha, meta): rgb [B, H, W, C] and
    alpha [B, H, W] when the cameras share one size, else lists [[H_b, W_b, C]] and [[H_b, W_b]]; meta a
    `SplatMeta`. `low_pass` px^2 is added to every 2D covariance (project.py). `backend`: "auto" (the Warp kernels:
    the tile walk on the CPU, the pixel walk on CUDA), "warp", "warp_tile", "warp_pixel" or "torch" (the dense twin,
    any dtype, tiny scenes); see rasterizer.py.

    Differentiable w.r.t. means, covars, colors and opacities; the backward computes only the gradients required
    (frozen colours: no colour gradient). Without gradients to keep (no grad mode, or no input that requires one) a
    Warp backend projects with the fused kernel (`rasterizer.project_and_reach`): the same images up to float
    rounding, without ~180 small torch operations per render.
    """
    B = len(cams)
    assert B > 0, "rasterization: no camera"
    given = {name: list(t.shape) for name, t in zip(("means", "covars", "colors", "opacities"),
                                                     (means, covars, colors, opacities))}
    means, covars, colors, opacities = (_batched(t, B, n, name) for t, n, name in (
        (means, 2, "means"), (covars, 3, "covars"), (colors, 2, "colors"), (opacities, 1, "opacities")))
    G = means.shape[1]
    assert means.shape == (B, G, 3), f"means: expected [{B}, G, 3] or [G, 3], got {given['means']}"
    for t, name, tail in ((covars, "covars", (3, 3)), (colors, "colors", colors.shape[2:]),
                          (opacities, "opacities", ())):
        assert t.shape == (B, G, *tail), \
            f"{name}: expected {[B, G, *tail]} or {[G, *tail]} (as means {given['means']}), got {given[name]}"
    grads = torch.is_grad_enabled() and any(t.requires_grad for t in (means, covars, colors, opacities))
    if backend != "torch" and not grads and means.dtype == torch.float32:
        proj = project_and_reach(means, covars, opacities, cams, low_pass=low_pass)
    else:
        proj = project_gaussians(means, covars, cams, low_pass=low_pass)
    rgb, alpha = rasterize(proj, colors, opacities, [(c.width, c.height) for c in cams], background, backend)
    return rgb, alpha, SplatMeta(radii=proj.radii, means2d=proj.means2d, depths=proj.depths)


def _batched(t: torch.Tensor, B: int, ndim: int, name: str) -> torch.Tensor:
    """`t` with its leading [B]: as given, or expanded (a view) where it is shared by every image (`ndim` dims)."""
    if t.ndim == ndim:
        return t.expand(B, *t.shape)
    assert t.ndim == ndim + 1 and t.shape[0] == B, \
        f"{name}: expected {ndim} dims (shared by the {B} images) or {ndim + 1} with a leading {B}, got {list(t.shape)}"
    return t
