"""Structured local Gaussian fields (`ModelConfig.field = "gaussians"`; a deviation from the paper, docs/fit.md).

The paper's structure is kept and only what a local field *is* changes: node i owns K 3D Gaussians instead of the
MLP F_i. Motion is decomposed exactly as in the paper:
1. skeleton: T_i from the body pose (Eq. 1, `deformer.node_transforms`);
2. node residual: the cVAE's Delta n_i moves the node (Eq. 3: n_i = T_i (n_bar_i + Delta n_i));
3. dynamic details: a small per-node decoder D^g_i(e_i, f_ik, mu_ik / sigma) (batched over a `nodes` dimension like
   the node MLPs) turns the node's detail embedding e_i, a Gaussian's appearance feature f_ik and its local position
   (in units of the Eq. 6 sigma, as the MLP fields see p_i) into a colour residual (spherical harmonics), an offset and
   an opacity change of that Gaussian. With the position it can bend or turn the node's patch per frame, which a
   loose garment needs (a node's own motion is T_i and a translation Delta n_i only).

A Gaussian k of node i lives in the node's local frame (Eq. 4 read backwards): its mean is
    x_ik = n_i + A_i (mu_ik + offset_ik)            (A_i: the 3x3 linear part of T_i)
its covariance Sigma_ik = A_i R_ik S_ik^2 R_ik^T A_i^T (R from a unit quaternion (w, x, y, z), S = exp(log-scales),
metres), its opacity sigmoid(logit_ik + delta_ik), its colour c = 0.5 + SH(d_local) with the viewing direction
d_local = A_i^-1 d (normalised) in the node's frame, so the view dependence turns with the body. The last decoder
layer starts at zero: at initialisation every frame renders the same static Gaussians.

Shading (`GaussianConfig.shading = "irradiance"`, a deviation beyond the paper): a capture's lights stay fixed in the
world while the body turns under them, and a Gaussian keeps one colour for every frame, so an unshaded field
averages each body part's shading over the training poses and cannot change it in a new one. With shading, a Gaussian
also has a unit normal n_ik in its node's frame (the template's normal nearest to where it starts; fixed, and a
relocated Gaussian takes its source's), its colour is read as an albedo, and the rendered colour is
    c = E(m_ik) (0.5 + SH(d_local)),   m_ik = A_i n_ik / |A_i n_ik|,   E(m) = max(0, 1 + sum_j l_j Y_j(m))
per colour channel, with Y_j the eight real spherical harmonics of orders 1 and 2 and l_j [8, 3] one learned
irradiance of the whole avatar (Ramamoorthi and Hanrahan 2001: order 2 holds a Lambertian surface's irradiance
under distant light to a few per cent; the order-0 term is the albedo's scale). l starts at zero (E = 1): the
first frames render as without it. E is folded into the colour coefficients (c is linear in them), so a posed
Gaussian's `sh` carries its shaded colour for every consumer (rasterizer, `.ply` export, density queries).

Initialisation: points drawn uniformly on the canonical template surface, each given to its nearest node (so a
node's Gaussians start within its support); K per node drawn from them (with replacement when a node has fewer).
A fit with hull nodes (fit/hull_nodes.py) adds points drawn uniformly in the hull survey's off-body cells (the loose
garment's volume, `off_body` of `initial_gaussians`), so the hull nodes nearest to them start there; a node that no
point falls to (an avatar built without the survey, e.g. before a checkpoint's weights replace its placeholders) gets
K points uniformly in a ball of a third of the support radius around it. Scales from the area each point covers.

Units: metres, world frame of the capture; colours in [0, 1]; SH constants of 3DGS (degree 0: 0.28209479).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn

from avatarctl.model.batched_mlp import BatchedLinear, BatchedMLP
from avatarctl.model.config import GaussianConfig
from avatarctl.splat.covariance import transformed_covariances
from avatarctl.splat.density import SH_C0, eval_sh


def sh_coefficients(degree: int) -> int:
    """Coefficients per colour channel of real spherical harmonics up to `degree`: (degree + 1)^2."""
    return (degree + 1) ** 2


def rgb_to_sh0(rgb: torch.Tensor) -> torch.Tensor:
    """Inverse of the degree-0 part of `eval_sh`: the DC coefficient that gives colour `rgb`."""
    return (rgb - 0.5) / SH_C0


@dataclass
class PosedGaussians:
    """The Gaussians of B frames, posed (world frame). G = nodes x per_node, node-major."""

    means: torch.Tensor  # [B, G, 3] metres
    covars: torch.Tensor  # [B, G, 3, 3] metres^2
    sh: torch.Tensor  # [B, G, S, 3] colour SH coefficients in the node's local frame
    opacities: torch.Tensor  # [B, G] in (0, 1)
    linear_inv: torch.Tensor  # [B, N, 3, 3] A_i^-1 of each node (viewing directions into the local frame)
    per_node: int  # K

    def colors(self, slot: int, camera_center: torch.Tensor) -> torch.Tensor:
        """[G, 3] colours of frame `slot` seen from `camera_center` [3] (world): SH at the local viewing direction."""
        return self.colors_batch([slot], camera_center[None])[0]

    def colors_batch(self, slots: list[int], camera_centers: torch.Tensor) -> torch.Tensor:
        """[B, G, 3] colours of frames `slots` (B of them) seen from `camera_centers` [B, 3] (world)."""
        contiguous = list(slots) == list(range(slots[0], slots[0] + len(slots))) if len(slots) else False
        sel = slice(slots[0], slots[0] + len(slots)) if contiguous else slots  # a slice: no index tensor to copy
        sh = self.sh[sel]  # [B, G, S, 3]
        if sh.shape[-2] == 1:
            return eval_sh(sh, sh.new_zeros(*sh.shape[:2], 3))
        B, N = len(slots), self.linear_inv.shape[1]
        d = self.means[sel] - camera_centers.to(self.means)[:, None, :]  # [B, G, 3]
        d_local = torch.einsum("bnij,bnkj->bnki", self.linear_inv[sel],
                               d.reshape(B, N, self.per_node, 3)).reshape(B, -1, 3)
        return eval_sh(sh, d_local / d_local.norm(dim=-1, keepdim=True).clamp(min=1e-12))


def _surface_samples(vertices: torch.Tensor, faces: torch.Tensor, count: int,
                     generator: torch.Generator) -> tuple[torch.Tensor, float]:
    """`count` points uniformly on the triangle mesh ([count, 3]) and the mesh area (square metres)."""
    tri = vertices[faces]  # [F, 3, 3]
    area = 0.5 * torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]).norm(dim=-1)  # [F]
    face = torch.multinomial(area, count, replacement=True, generator=generator)
    u, v = torch.rand(count, generator=generator), torch.rand(count, generator=generator)
    flip = u + v > 1
    u, v = torch.where(flip, 1 - u, u), torch.where(flip, 1 - v, v)
    t = tri[face]
    return t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0]), float(area.sum())


def initial_gaussians(vertices: torch.Tensor, faces: torch.Tensor, node_rest: torch.Tensor, per_node: int,
                      support_radius: float, seed: int, off_body: tuple[torch.Tensor, float] | None = None
                      ) -> tuple[torch.Tensor, torch.Tensor]:
    """Initial local means [N, K, 3] (metres, relative to the canonical node n_bar_i) and log-scales [N, K, 3]; see
    the module docstring. vertices [V, 3] and node_rest [N, 3] canonical, faces [F, 3]. `off_body` (cells [C, 3],
    side): the hull survey's persistent off-body cells in canonical space (fit/hull_nodes.py): the loose garment's
    volume. Points drawn uniformly in them join the surface points (as many per cell as the surface has per 5 cm
    square), so the nodes nearest to them (the hull nodes) start their Gaussians where the garment is."""
    gen = torch.Generator().manual_seed(int(seed) + 4_242)
    N, K = node_rest.shape[0], per_node
    pts, area = _surface_samples(vertices.detach().float().cpu(), faces.cpu(), 8 * N * K, gen)
    per_point_area = area / pts.shape[0]
    spacing = torch.full((pts.shape[0],), math.sqrt(per_point_area))  # [P] metres between neighbouring points
    if off_body is not None and off_body[0].shape[0]:
        cells, side = off_body[0].detach().float().cpu(), float(off_body[1])
        m = max(1, round(side * side / per_point_area))
        extra = cells.repeat_interleave(m, 0) + (torch.rand(cells.shape[0] * m, 3, generator=gen) - 0.5) * side
        pts = torch.cat([pts, extra])
        spacing = torch.cat([spacing, torch.full((extra.shape[0],), side / m ** (1 / 3))])
    rest = node_rest.detach().float().cpu()
    owner = torch.cat([torch.cdist(c, rest).argmin(dim=1) for c in pts.split(16_384)])  # [P] nearest node
    means = torch.empty(N, K, 3)
    log_scales = torch.empty(N, K, 3)
    order = torch.argsort(owner, stable=True)
    counts = torch.bincount(owner, minlength=N).tolist()
    start = 0
    for i, c in enumerate(counts):
        mine = pts[order[start:start + c]]
        start += c
        if c == 0:  # an off-body (hull) node: a ball of support / 3
            r = support_radius / 3
            d = torch.randn(K, 3, generator=gen)
            d = d / d.norm(dim=-1, keepdim=True) * r * torch.rand(K, 1, generator=gen) ** (1 / 3)
            means[i] = d
            log_scales[i] = math.log(0.5 * r / K ** (1 / 3))
            continue
        pick = torch.randperm(c, generator=gen)[:K] if c >= K else torch.randint(c, (K,), generator=gen)
        means[i] = mine[pick] - rest[i]
        gap = spacing[order[start - c:start]].mean() * math.sqrt(c / K)  # spacing of K points over the same area
        log_scales[i] = math.log(max(0.5 * float(gap), 1e-4))
    return means, log_scales


def irradiance_basis(normals: torch.Tensor) -> torch.Tensor:
    """[..., 3] unit normals -> [..., 8] the real spherical harmonics of orders 1 and 2, without their constant factors
    (the learned irradiance absorbs them): y, z, x, xy, yz, 3z^2 - 1, xz, x^2 - y^2."""
    x, y, z = normals.unbind(-1)
    return torch.stack([y, z, x, x * y, y * z, 3 * z * z - 1, x * z, x * x - y * y], -1)


def initial_normals(vertices: torch.Tensor, faces: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """[P, 3] canonical points -> [P, 3] unit normals: the area-weighted vertex normal of the template vertex nearest to
    each (vertices [V, 3], faces [F, 3] of the canonical template). The faces' winding gives the side (outward for
    anny's); a template wound inward flips every normal alike, which the learned irradiance absorbs (its order-1 terms
    change sign, its order-2 terms are even)."""
    from scipy.spatial import cKDTree

    from avatarctl.geometry.normals import vertex_normals

    v = vertices.detach().cpu().double().numpy()
    vn = vertex_normals(v, faces.cpu().numpy())
    _, nearest = cKDTree(v).query(points.detach().cpu().double().numpy())  # a tree: no [P, V] distance matrix
    return torch.as_tensor(vn[nearest], dtype=torch.float32)


def shade(sh: torch.Tensor, linear: torch.Tensor, normals: torch.Tensor, light: torch.Tensor) -> torch.Tensor:
    """The module docstring's shading folded into the colour coefficients: sh [B, N, K, S, 3] (albedo), linear
    [B, N, 3, 3] A_i, normals [N, K, 3] n_ik (node frame), light [8, 3] l -> [B, N, K, S, 3] whose colour is E(m) times
    the albedo's."""
    m = (linear[:, :, None] * normals[None, :, :, None, :]).sum(-1)  # [B, N, K, 3] A_i n_ik
    m = m / m.norm(dim=-1, keepdim=True).clamp(min=1e-12)
    E = (1.0 + irradiance_basis(m) @ light).clamp(min=0.0)  # [B, N, K, 3]
    dc = (E * (0.5 + SH_C0 * sh[..., 0, :]) - 0.5) / SH_C0  # E (0.5 + SH_C0 sh_0) = 0.5 + SH_C0 dc
    return torch.cat([dc[..., None, :], E[..., None, :] * sh[..., 1:, :]], dim=-2)


class NodeGaussians(nn.Module):
    """The N nodes' K Gaussians and their per-node decoder (see the module docstring)."""

    def __init__(self, cfg: GaussianConfig, num_nodes: int, embed_dim: int, init_means: torch.Tensor,
                 init_log_scales: torch.Tensor, sigma: float = 0.05, init_normals: torch.Tensor | None = None):
        super().__init__()
        N, K = num_nodes, cfg.per_node
        assert init_means.shape == (N, K, 3), f"init_means: expected [{N}, {K}, 3], got {tuple(init_means.shape)}"
        self.cfg = cfg
        self.num_nodes, self.per_node = N, K
        S = sh_coefficients(cfg.sh_degree)
        self.num_sh = S
        self.means = nn.Parameter(init_means.clone().float())  # [N, K, 3] local, metres
        self.log_scales = nn.Parameter(init_log_scales.clone().float())  # [N, K, 3]
        self.quats = nn.Parameter(torch.tensor([1.0, 0.0, 0.0, 0.0]).repeat(N, K, 1))  # [N, K, 4] (w, x, y, z)
        p = cfg.init_opacity
        self.opacity_logits = nn.Parameter(torch.full((N, K), math.log(p / (1 - p))))  # [N, K]
        self.sh = nn.Parameter(torch.zeros(N, K, S, 3))  # [N, K, S, 3]: grey at the start
        self.features = nn.Parameter(0.1 * torch.randn(N, K, cfg.feature_dim))  # [N, K, F]
        self.embed = BatchedLinear(N, embed_dim, cfg.decoder_width, bias=False)  # e_i's first-layer term
        self.coord_scale = 1.0 / sigma  # the decoder sees mu_ik / sigma (Eq. 6 sigma, metres)
        self.decoder = BatchedMLP(N, [cfg.feature_dim + 3, cfg.decoder_width, 3 * S + 3 + 1], last_init_scale=0.0)
        self.shaded = cfg.shading == "irradiance"
        if self.shaded:
            if init_normals is None:
                raise ValueError("shading 'irradiance' needs the Gaussians' initial normals")
            assert init_normals.shape == (N, K, 3), f"init_normals {list(init_normals.shape)}, expected [{N}, {K}, 3]"
            self.register_buffer("normals", init_normals.clone().float())  # [N, K, 3] n_ik, node frame (fixed)
            self.light = nn.Parameter(torch.zeros(8, 3))  # l: E = 1 + sum_j l_j Y_j, per colour channel

    def gaussian_parameters(self) -> dict[str, list[nn.Parameter]]:
        """The per-Gaussian parameters by learning-rate group (names of `GaussianConfig.lr_*`)."""
        return {"lr_means": [self.means], "lr_scales": [self.log_scales], "lr_quats": [self.quats],
                "lr_opacity": [self.opacity_logits],
                "lr_colors": [self.sh, self.features] + ([self.light] if self.shaded else [])}

    def forward(self, transforms: torch.Tensor, centers: torch.Tensor, embed: torch.Tensor) -> PosedGaussians:
        """transforms [B, N, 4, 4] T_i (Eq. 1), centers [B, N, 3] posed nodes n_i (Eq. 3), embed [B, N, E] e_i ->
        the posed Gaussians of the B frames."""
        B, N, K, S = centers.shape[0], self.num_nodes, self.per_node, self.num_sh
        F = self.features.shape[-1]
        bias = self.embed(embed.transpose(0, 1))  # [N, B, width]
        x = torch.cat([self.features, self.means * self.coord_scale], -1)  # [N, K, F + 3]
        x = x[:, None].expand(N, B, K, F + 3).reshape(N, B * K, F + 3)
        first = bias[:, :, None, :].expand(N, B, K, bias.shape[-1]).reshape(N, B * K, -1)
        out = self.decoder(x, first_bias=first).reshape(N, B, K, -1).transpose(0, 1)  # [B, N, K, 3S + 4]
        sh = self.sh[None] + out[..., :3 * S].reshape(B, N, K, S, 3)
        offset = out[..., 3 * S:3 * S + 3] * self.cfg.offset_scale
        opacity = torch.sigmoid(self.opacity_logits[None] + out[..., -1])  # [B, N, K]
        A = transforms[..., :3, :3]  # [B, N, 3, 3]
        if self.shaded:
            sh = shade(sh, A, self.normals, self.light)
        local = self.means[None] + offset  # [B, N, K, 3]
        means = centers[:, :, None, :] + (A[:, :, None] * local[..., None, :]).sum(-1)
        covars = transformed_covariances(A, self.quats, self.log_scales)  # [B, N, K, 3, 3] M M^T, M = A R S
        return PosedGaussians(means=means.reshape(B, N * K, 3), covars=covars.reshape(B, N * K, 3, 3),
                              sh=sh.reshape(B, N * K, S, 3), opacities=opacity.reshape(B, N * K),
                              linear_inv=torch.linalg.inv_ex(A).inverse, per_node=K)  # inv_ex: no sync for a check
