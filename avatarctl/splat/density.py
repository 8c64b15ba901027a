"""Gaussians as a density with colour at arbitrary points (what the mesh export of a Gaussian avatar samples):

    sigma(x) = sum_g w_g exp(-q_g / 2),   q_g = (x - mu_g)^T Sigma_g^-1 (x - mu_g), over the g with q_g <= CUTOFF^2
    rgb(x)   = sum_g w_g exp(-q_g / 2) c_g(dir) / sigma(x),   c_g(dir) = eval_sh(sh_g, M_g dir / |M_g dir|)

w_g is the caller's (the model gives each Gaussian its optical depth over sqrt(2 pi) det(Sigma)^(1/6)); M_g maps a
world direction into the frame of g's SH coefficients (a node's A^-1; the identity when None).

`gaussian_field_at` (Warp, CPU or CUDA): the Gaussians are binned into cubic cells by the box of their cut-off
ellipsoid (count, prefix sum, fill: what the rasterizer does with screen tiles), then one thread per point sums over
its cell's list. On the CPU a cell's list is in Gaussian order (deterministic sums); on CUDA the order of the adds
varies from run to run (float rounding). `gaussian_field_at_torch` is the dense twin (every point against every
Gaussian; tiny scenes).
"""

from __future__ import annotations

import torch

SH_C0 = 0.28209479177387814  # 3DGS's real spherical-harmonic constants, degrees 0 and 1
SH_C1 = 0.4886025119029199
CUTOFF = 4.0  # Mahalanobis radius beyond which a Gaussian adds nothing (exp(-8) = 3.4e-4 of its peak)
MAX_CELLS = 4_000_000  # the cell grid grows coarser past this many cells
MAX_ENTRIES = 32_000_000  # ... or past this many (cell, Gaussian) entries (a few huge Gaussians cover many cells)


def eval_sh(sh: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Colour from SH coefficients (3DGS's basis and signs): sh [..., S, 3] (S = 1 or 4), dirs [..., 3] unit ->
    rgb [..., 3] = max(0, 0.5 + sum_s Y_s(d) sh_s)."""
    out = SH_C0 * sh[..., 0, :]
    if sh.shape[-2] > 1:
        x, y, z = dirs[..., 0:1], dirs[..., 1:2], dirs[..., 2:3]
        out = out - SH_C1 * y * sh[..., 1, :] + SH_C1 * z * sh[..., 2, :] - SH_C1 * x * sh[..., 3, :]
    return torch.clamp(out + 0.5, min=0.0)


def _check(points, dirs, means, covars, weights, sh, dir_maps) -> None:
    P, G = points.shape[0], means.shape[0]
    assert points.shape == (P, 3) and dirs.shape == (P, 3), f"points {list(points.shape)}, dirs {list(dirs.shape)}"
    assert covars.shape == (G, 3, 3) and weights.shape == (G,) and sh.ndim == 3 and sh.shape[0] == G \
        and sh.shape[1] in (1, 4) and sh.shape[2] == 3, \
        f"means {list(means.shape)}, covars {list(covars.shape)}, weights {list(weights.shape)}, sh {list(sh.shape)}"
    assert dir_maps is None or dir_maps.shape == (G, 3, 3), f"dir_maps {list(dir_maps.shape)}"


def gaussian_field_at_torch(points: torch.Tensor, dirs: torch.Tensor, means: torch.Tensor, covars: torch.Tensor,
                            weights: torch.Tensor, sh: torch.Tensor, dir_maps: torch.Tensor | None = None,
                            chunk: int = 1024) -> tuple[torch.Tensor, torch.Tensor]:
    """The module docstring's field, dense (the twin of `gaussian_field_at`): points, dirs [P, 3]; means [G, 3],
    covars [G, 3, 3], weights [G], sh [G, S, 3], dir_maps [G, 3, 3] or None -> rgb [P, 3], sigma [P]."""
    _check(points, dirs, means, covars, weights, sh, dir_maps)
    prec = torch.linalg.inv(covars)
    rgb, sigma = [], []
    for s in range(0, points.shape[0], chunk):
        d = points[s:s + chunk, None, :] - means[None]  # [c, G, 3]
        q = torch.einsum("cgi,gij,cgj->cg", d, prec, d)
        w = torch.where(q <= CUTOFF ** 2, weights * torch.exp(-0.5 * q), torch.zeros_like(q))
        v = dirs[s:s + chunk, None, :].expand(-1, means.shape[0], 3)
        if dir_maps is not None:
            v = torch.einsum("gij,cgj->cgi", dir_maps, v)
        col = eval_sh(sh[None].expand(v.shape[0], -1, -1, -1), torch.nn.functional.normalize(v, dim=-1))
        sigma.append(w.sum(1))
        rgb.append((w[..., None] * col).sum(1))
    total = torch.cat(sigma) if sigma else points.new_zeros(0)
    rgb_t = torch.cat(rgb) if rgb else points.new_zeros(0, 3)
    return rgb_t / total.clamp(min=1e-12)[:, None], total


def gaussian_field_at(points: torch.Tensor, dirs: torch.Tensor, means: torch.Tensor, covars: torch.Tensor,
                      weights: torch.Tensor, sh: torch.Tensor, dir_maps: torch.Tensor | None = None
                      ) -> tuple[torch.Tensor, torch.Tensor]:
    """`gaussian_field_at_torch`'s result from the Warp kernels (module docstring), float32, no gradients."""
    import warp as wp

    from avatarctl.splat.rasterizer import _kernels, torch_stream

    _check(points, dirs, means, covars, weights, sh, dir_maps)
    P, G, dev = points.shape[0], means.shape[0], points.device
    if P == 0 or G == 0:
        return points.new_zeros(P, 3), points.new_zeros(P)
    k = _kernels()

    def f32(t: torch.Tensor) -> torch.Tensor:
        return t.detach().to(device=dev, dtype=torch.float32).contiguous()

    pts, dirs_, mu, cov, wts = f32(points), f32(dirs), f32(means), f32(covars), f32(weights)
    prec = torch.linalg.inv_ex(cov).inverse.contiguous()
    halves = (CUTOFF * torch.sqrt(torch.diagonal(cov, dim1=-2, dim2=-1).clamp(min=0))).contiguous()  # [G, 3]
    lo, hi = pts.min(0).values, pts.max(0).values
    cell = max(float(torch.quantile(halves.max(-1).values.cpu(), 0.75)), 1e-4)
    lo_v = wp.vec3(*lo.cpu().tolist())
    mu_w, half_w = wp.from_torch(mu, dtype=wp.vec3), wp.from_torch(halves, dtype=wp.vec3)
    maps = f32(dir_maps) if dir_maps is not None else torch.eye(3, device=dev).expand(G, 3, 3).contiguous()
    sigma, rgb = torch.empty(P, device=dev), torch.empty(P, 3, device=dev)
    with torch_stream(dev):
        while True:  # cells of the common Gaussian's size, coarser where the grid or its lists would grow too big
            dims = [int(x) + 1 for x in torch.ceil((hi - lo) / cell).cpu().tolist()]
            if dims[0] * dims[1] * dims[2] > MAX_CELLS:
                cell *= 1.26
                continue
            dims_v = wp.vec3i(*dims)
            counts = torch.zeros(dims[0] * dims[1] * dims[2], dtype=torch.int32, device=dev)
            wp.launch(k.count_cells, dim=G, inputs=[mu_w, half_w, lo_v, cell, dims_v, wp.from_torch(counts)],
                      device=str(dev))
            if int(counts.sum(dtype=torch.int64)) <= MAX_ENTRIES:
                break
            cell *= 1.26
        start = torch.cat([counts.new_zeros(1), torch.cumsum(counts, 0, dtype=torch.int32)])
        ids = torch.empty(int(start[-1]), dtype=torch.int32, device=dev)
        cursor = start[:-1].clone()
        wp.launch(k.fill_cells, dim=G, inputs=[mu_w, half_w, lo_v, cell, dims_v, wp.from_torch(cursor),
                                               wp.from_torch(ids)], device=str(dev))
        wp.launch(k.density_at_points, dim=P, inputs=[
            wp.from_torch(pts, dtype=wp.vec3), wp.from_torch(dirs_, dtype=wp.vec3), lo_v, cell, dims_v,
            wp.from_torch(start), wp.from_torch(ids), mu_w, wp.from_torch(prec, dtype=wp.mat33), wp.from_torch(wts),
            wp.from_torch(f32(sh).reshape(G, -1)), wp.from_torch(maps, dtype=wp.mat33), CUTOFF ** 2,
            wp.from_torch(sigma), wp.from_torch(rgb, dtype=wp.vec3)], device=str(dev))
    return rgb / sigma.clamp(min=1e-12)[:, None], sigma
