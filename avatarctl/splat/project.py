"""Projection of 3D Gaussians to screen-space 2D Gaussians (EWA splatting, Zwicker et al. 2001), pure torch.

For a Gaussian with world mean mu and covariance Sigma seen by camera (K, R, T):

    t = R mu + T                         camera coordinates, metres (z = depth)
    mean2d = K[:2, :2] (t_x / t_z, t_y / t_z) + K[:2, 2]           pixels
    J = K[:2, :2] [[1/t_z, 0, -t_x/t_z^2], [0, 1/t_z, -t_y/t_z^2]]   Jacobian of the projection at t
    Sigma2d = J R Sigma R^T J^T + s I    (the low-pass s, px^2: 3DGS's 0.3 makes every splat at least ~1 px wide;
                                          the callers choose it, `LOW_PASS` by default)
    conic = Sigma2d^-1 = [[a, b], [b, c]]  stored as (a, b, c)
    radius = ceil(3 sqrt(lambda_max(Sigma2d)))  pixels

As in 3DGS, J is evaluated with t_x / t_z and t_y / t_z clamped to 1.3x the half field of view, so that a Gaussian far
outside the window does not get a huge footprint (the mean itself is not clamped). A Gaussian is culled (radius 0)
when its depth is not beyond `near`, when Sigma2d is degenerate, or when its footprint misses the image.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch

from avatarctl.splat.camera import SplatCamera

LOW_PASS = 0.3  # px^2 added to the diagonal of Sigma2d by default (3DGS's value)
FOV_CLAMP = 1.3  # J is evaluated inside 1.3x the half field of view (3DGS)


@dataclass
class Projected:
    """Screen-space Gaussians, one row per input Gaussian (culled rows have radius 0 and zero conic).

    Two layouts, one type: `project_gaussians` returns rows per image, fields [B, G, ...] (B images of G Gaussians);
    the compositing layer (`rasterizer.Canvas`, `rasterizer.bin_gaussians`, `_torch_impl.rasterize_torch`) takes the
    B images laid out on one canvas, fields [B * G, ...], written [G, ...] below."""

    means2d: torch.Tensor  # [G, 2] pixels (pixel centres at integers)
    conics: torch.Tensor  # [G, 3] (a, b, c) of the inverse 2D covariance [[a, b], [b, c]], 1/px^2
    depths: torch.Tensor  # [G] camera z, metres (sort key, front to back)
    radii: torch.Tensor  # [G] int32 pixels, ceil(3 sqrt(lambda_max)); 0 = culled
    # [G, 4] int32 (x0, y0, x1, y1) inclusive: the window a splat may count in, where several images share one
    # canvas (`rasterizer.Canvas`); None = the whole image
    bounds: torch.Tensor | None = None
    # [G, 4] int32: `rasterizer.reach` already computed (by the fused `rasterizer.project_and_reach`); None = binning
    # computes it
    reach: torch.Tensor | None = None


def footprint(means2d: torch.Tensor, radii: torch.Tensor, width, height) -> torch.Tensor:
    """The pixels a splat may touch: the square mean +- radius, clipped to the image.

    means2d [..., G, 2], radii [..., G], width / height ints or tensors broadcastable to [..., G] (one size per
    camera) -> [..., G, 4] int32 (x0, y0, x1, y1), inclusive pixel bounds; x0 > x1 or y0 > y1 where the splat touches
    no pixel (culled or off screen). Pixel x is inside when ceil(mx - r) <= x <= floor(mx + r).
    """
    m = means2d.detach()
    r = radii.to(m.dtype)
    x0 = torch.ceil(m[..., 0] - r).clamp(min=0)
    y0 = torch.ceil(m[..., 1] - r).clamp(min=0)
    x1 = torch.minimum(torch.floor(m[..., 0] + r), torch.as_tensor(width, dtype=m.dtype, device=m.device) - 1)
    y1 = torch.minimum(torch.floor(m[..., 1] + r), torch.as_tensor(height, dtype=m.dtype, device=m.device) - 1)
    box = torch.stack([x0, y0, x1, y1], dim=-1)
    box = torch.where((radii > 0)[..., None], box,
                      torch.tensor([0.0, 0.0, -1.0, -1.0], dtype=m.dtype, device=m.device))
    return box.to(torch.int32)


def within_bounds(box: torch.Tensor, proj: Projected) -> torch.Tensor:
    """[G, 4] int32 pixel boxes cut to each splat's window `proj.bounds` (unchanged where it is None)."""
    if proj.bounds is None:
        return box
    return torch.cat([torch.maximum(box[:, :2], proj.bounds[:, :2]), torch.minimum(box[:, 2:], proj.bounds[:, 2:])], -1)


def project_gaussians(means: torch.Tensor,  # [B, G, 3] world, metres: the Gaussians seen by camera b
                      covars: torch.Tensor,  # [B, G, 3, 3] world covariance, metres^2 (symmetric PSD)
                      cams: Sequence[SplatCamera], near: float = 0.01, low_pass: float = LOW_PASS) -> Projected:
    """World Gaussians -> screen-space Gaussians seen by B cameras at once (one set of operations, whatever B; each
    camera its own window size; one image is B = 1) -> a `Projected` with fields [B, G, ...]. See the module
    docstring; `low_pass` px^2 is added to Sigma2d's diagonal. Differentiable w.r.t. means and covars through
    autograd; radii carry no gradient. Works in the dtype of `means` (float32 or float64)."""
    B, G = means.shape[:2]
    assert means.shape == (B, G, 3) and len(cams) == B, \
        f"means: expected [{len(cams)}, G, 3] (one row per camera), got {list(means.shape)}"
    assert covars.shape == (B, G, 3, 3), f"covars: expected [{B}, {G}, 3, 3], got {list(covars.shape)}"
    dev, dt = means.device, means.dtype
    K, R, T = (torch.stack([getattr(c, n) for c in cams]).to(device=dev, dtype=dt) for n in ("K", "R", "T"))
    width, height = torch.tensor([[float(c.width), float(c.height)] for c in cams], dtype=dt, device=dev).unbind(-1)
    width, height = width[:, None], height[:, None]  # [B, 1]
    t = torch.baddbmm(T[:, None, :], means, R.transpose(1, 2))  # [B, G, 3] camera coordinates
    z = t[..., 2]
    in_front = z > near
    inv_z = 1.0 / torch.where(in_front, z, torch.ones_like(z))  # culled rows: finite values, zero gradient
    x, y = t[..., 0] * inv_z, t[..., 1] * inv_z  # [B, G]
    fx, skew, cx, fy, cy = (K[:, i, j, None] for i, j in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2)))  # [B, 1] each
    means2d = torch.stack([fx * x + skew * y + cx, fy * y + cy], dim=-1)  # [B, G, 2]

    half_x, half_y = 0.5 * width / fx, 0.5 * height / fy  # tan of the half field of view
    margin = FOV_CLAMP - 1.0
    xc = torch.clamp(x, -(cx / fx + margin * half_x), (width - cx) / fx + margin * half_x)
    yc = torch.clamp(y, -(cy / fy + margin * half_y), (height - cy) / fy + margin * half_y)
    # rows of M = K[:2, :2] J R, J = d(x/z, y/z)/dt = [[1, 0, -xc], [0, 1, -yc]] / z:
    R0, R1, R2 = (R[:, None, i, :] for i in range(3))  # [B, 1, 3]
    row_x = (R0 - xc[..., None] * R2) * inv_z[..., None]  # [B, G, 3]
    row_y = (R1 - yc[..., None] * R2) * inv_z[..., None]
    m0, m1 = fx[..., None] * row_x + skew[..., None] * row_y, fy[..., None] * row_y  # [B, G, 3] each
    cov_m = torch.bmm(covars.reshape(B * G, 3, 3), torch.stack([m0, m1], dim=-1).reshape(B * G, 3, 2))
    cov_m = cov_m.reshape(B, G, 3, 2)  # Sigma M^T
    a = (m0 * cov_m[..., 0]).sum(-1) + low_pass  # Sigma2d = M Sigma M^T + low_pass I = [[a, b], [b, c]]
    b = (m1 * cov_m[..., 0]).sum(-1)
    c = (m1 * cov_m[..., 1]).sum(-1) + low_pass
    det = a * c - b * b
    ok = in_front & (det > 0) & torch.isfinite(det)
    inv_det = torch.where(ok, 1.0 / torch.where(ok, det, torch.ones_like(det)), torch.zeros_like(det))
    conics = torch.stack([c * inv_det, -b * inv_det, a * inv_det], dim=-1)
    means2d = means2d * ok[..., None]

    with torch.no_grad():
        mid = 0.5 * (a + c)
        lam_max = mid + torch.sqrt(torch.clamp(mid * mid - det, min=0.0))
        radii = torch.where(ok, torch.ceil(3.0 * torch.sqrt(lam_max)), torch.zeros_like(lam_max)).to(torch.int32)
        box = footprint(means2d, radii, width, height)
        radii = torch.where((box[..., 0] <= box[..., 2]) & (box[..., 1] <= box[..., 3]), radii,
                            torch.zeros_like(radii))
    return Projected(means2d=means2d, conics=conics, depths=t[..., 2], radii=radii)
