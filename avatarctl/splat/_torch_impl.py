"""The pure-PyTorch twin of the Warp rasterizer: the reference for its semantics, dense and slow (tiny scenes).

3DGS alpha compositing (Kerbl et al. 2023, Eq. 3), per pixel p and the splats sorted front to back by depth:

    d = p - mean2d,   power = -0.5 (a dx^2 + c dy^2) - b dx dy           (skipped where power > 0)
    alpha = min(ALPHA_MAX, o exp(power))                              (skipped where alpha < ALPHA_MIN)
    a splat only touches the pixels of its footprint (project.footprint: mean +- radius), within its window
    (`Projected.bounds`) where several images share one canvas
    T_0 = 1;  a splat whose T (1 - alpha) would fall below T_MIN ends the pixel and is NOT added;
    otherwise C += T alpha c,  T *= 1 - alpha
    rgb = C + T_final background,   alpha = 1 - T_final

Autograd gives the gradients; the min(ALPHA_MAX, .) clamp passes none where it is active.
"""

from __future__ import annotations

import torch

from avatarctl.splat.project import Projected, footprint, within_bounds

TILE = 16  # px, the side of a screen tile (binning and the kernels' unit of work)
ALPHA_MIN = 1.0 / 255.0  # a splat fainter than this at a pixel is skipped there
ALPHA_MAX = 0.99  # alpha is clamped here (keeps 1 - alpha invertible for the backward pass)
T_MIN = 1e-4  # a pixel is finished before its transmittance drops below this


def rasterize_torch(proj: Projected, colors: torch.Tensor,  # [G, C]
                    opacities: torch.Tensor,  # [G] in [0, 1]
                    width: int, height: int, background: torch.Tensor,  # [C]
                    cutoffs: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """-> rgb [H, W, C] composited over the background, alpha [H, W]. Builds a dense [H * W, G] alpha matrix.

    cutoffs=False drops the footprint, ALPHA_MIN and T_MIN cut-offs (every visible splat reaches every pixel): the
    image is then a smooth function of the inputs, for finite-difference checks of the gradients.
    """
    dtype, device = proj.means2d.dtype, proj.means2d.device
    visible = torch.nonzero(proj.radii > 0).squeeze(-1)
    order = visible[torch.argsort(proj.depths.detach()[visible], stable=True)]  # [visible] front to back
    m, con = proj.means2d[order], proj.conics[order]
    ys, xs = torch.meshgrid(torch.arange(height, device=device), torch.arange(width, device=device), indexing="ij")
    px, py = xs.reshape(-1, 1).to(dtype), ys.reshape(-1, 1).to(dtype)  # [P, 1]
    dx, dy = px - m[:, 0], py - m[:, 1]  # [P, visible]
    power = -0.5 * (con[:, 0] * dx * dx + con[:, 2] * dy * dy) - con[:, 1] * dx * dy
    power = torch.where(power <= 0, power, torch.full_like(power, -torch.inf))
    alpha = torch.clamp(opacities[order] * torch.exp(power), max=ALPHA_MAX)  # [P, visible]
    if cutoffs:
        box = within_bounds(footprint(proj.means2d, proj.radii, width, height), proj)[order]  # [visible, 4]
        inside = (px >= box[:, 0]) & (px <= box[:, 2]) & (py >= box[:, 1]) & (py <= box[:, 3])
        alpha = torch.where(inside & (alpha >= ALPHA_MIN), alpha, torch.zeros_like(alpha))
        with torch.no_grad():
            alive = torch.cumprod(1 - alpha, dim=1) >= T_MIN  # the splat that would cross T_MIN and all behind it
        alpha = torch.where(alive, alpha, torch.zeros_like(alpha))
    trans = torch.cumprod(torch.cat([alpha.new_ones(alpha.shape[0], 1), 1 - alpha], dim=1), dim=1)  # [P, visible + 1]
    rgb = (alpha * trans[:, :-1]) @ colors[order] + trans[:, -1:] * background
    return rgb.reshape(height, width, -1), (1 - trans[:, -1]).reshape(height, width)
