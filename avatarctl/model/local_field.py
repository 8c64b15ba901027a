"""The one interface of a kind of local field F_i: `LocalField`, and its two kinds.

The paper's local radiance fields are small MLPs queried along camera rays (Eq. 5-7, volume-rendered); the deviation
`model.field = "gaussians"` makes each F_i a set of K 3D Gaussians, rasterized (model/gaussian_field.py). Everything
that differs between the two is asked of the avatar's `field_kind`, never by testing which kind it holds:

==================  ==========================================  ===============================================
                    `RayMarched` ("mlp", and the LBS baseline)  `Rasterized` ("gaussians")
==================  ==========================================  ===============================================
modules             `build`: F_i MLPs (or one canonical MLP),   `build`: K Gaussians per node + a decoder
                    heads G / H, occupancy grids when on
trains on           `trains_on = "rays"` (fit/steps.py draws    `trains_on = "crops"`: whole image crops,
                    scattered rays, Eq. 12)                     L1 + D-SSIM + mask
density at points   `query`: heads on the fused feature         `query`: the Gaussians as a density (mesh export)
density control     none (occupancy updates in the forward)     `density_control`: relocation of dead Gaussians
a whole view        `render_view`: candidate rays, marched      `render_view`: the image rasterized at once
                    in chunks (`render.engine.march_view`)      (`render.engine.rasterize_view`)
splats              `splats = False`                            `splats = True`: `.ply` splat files, the player,
                                                                the viewer's splat page, meshes coloured from
                                                                rasterized views
==================  ==========================================  ===============================================

A kind holds no state (the parameters live in the avatar's modules): one instance per kind, `FIELD_KINDS`, looked
up once from the config by `field_kind`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol

import torch

from avatarctl.model.config import ModelConfig

if TYPE_CHECKING:
    from avatarctl.body.base import BodyTemplate
    from avatarctl.geometry.cameras import Camera
    from avatarctl.model.avatar import NodeState, SlrfAvatar
    from avatarctl.progress import ProgressFn
    from avatarctl.render.engine import ViewRender

    import numpy as np


class LocalField(Protocol):
    """What the fit, render, eval, export and the viewer ask of a kind of local field (module docstring)."""

    name: str  # the `ModelConfig.field` value
    trains_on: str  # "rays" | "crops": what one training step's batch holds (fit/steps.py)
    splats: bool  # the field is a set of 3D Gaussians (splat files, the viewer's splat page)

    def build(self, avatar: "SlrfAvatar", template: "BodyTemplate", rest: torch.Tensor, seed: int,
              off_body: tuple[torch.Tensor, float] | None) -> None:
        """Create the field's modules and buffers on `avatar` (rest [N, 3]: the canonical node positions)."""
        ...

    def query(self, avatar: "SlrfAvatar", points: torch.Tensor, dirs: torch.Tensor, point_frame: torch.Tensor,
              state: "NodeState", candidates: tuple[torch.Tensor, torch.Tensor] | None = None
              ) -> tuple[torch.Tensor, torch.Tensor, dict[str, float]]:
        """Colour and density at posed points: points / dirs [P, 3], point_frame [P] -> rgb [P, 3], sigma [P], stats."""
        ...

    def density_control(self, avatar: "SlrfAvatar", optimizer: torch.optim.Optimizer, step: int, seed: int) -> int:
        """After optimiser step `step` (1-based): the field's own density control; -> how many primitives moved."""
        ...

    def render_view(self, avatar: "SlrfAvatar", state: "NodeState", slot: int, camera: "Camera",
                    background: tuple[float, float, float], max_rays_per_chunk: int,
                    pixel_mask: "np.ndarray | None", progress: "ProgressFn | None") -> "ViewRender":
        """Frame `slot` of `state` seen by `camera` (a pinhole camera, checked by `render.engine.render_view`)."""
        ...


class RayMarched:
    """The paper's local fields: MLPs queried at ray samples and volume-rendered (also the pose-only baseline's one
    canonical MLP)."""

    name = "mlp"
    trains_on = "rays"
    splats = False

    def build(self, avatar: "SlrfAvatar", template: "BodyTemplate", rest: torch.Tensor, seed: int,
              off_body: tuple[torch.Tensor, float] | None) -> None:
        from avatarctl.model.field import CanonicalField, NodeFields, RadianceHeads
        from avatarctl.model.occupancy import UNSEEN

        cfg = avatar.cfg
        if cfg.variant == "slrf":
            avatar.fields = NodeFields(cfg.num_nodes, cfg.pe_coords, cfg.embed_dim, cfg.node_width, cfg.node_depth,
                                       cfg.feature_dim)
        else:  # one canonical network of comparable total capacity: twice as wide and two layers deeper than an F_i
            avatar.canonical = CanonicalField(cfg.pe_coords, 2 * cfg.node_width, cfg.node_depth + 2, cfg.feature_dim)
        avatar.heads = RadianceHeads(cfg.feature_dim, cfg.head_width, cfg.pe_views)
        if cfg.occupancy.enabled:  # [N * res^3] per-node occupancy grids (model/occupancy.py), saved with the weights
            avatar.register_buffer("occupancy", torch.full((cfg.num_nodes * cfg.occupancy.res ** 3,), UNSEEN))
            avatar.register_buffer("occupancy_updates", torch.zeros((), dtype=torch.long))  # training steps seen

    def query(self, avatar: "SlrfAvatar", points: torch.Tensor, dirs: torch.Tensor, point_frame: torch.Tensor,
              state: "NodeState", candidates: tuple[torch.Tensor, torch.Tensor] | None = None
              ) -> tuple[torch.Tensor, torch.Tensor, dict[str, float]]:
        return avatar._query_heads(points, dirs, point_frame, state, candidates)

    def density_control(self, avatar: "SlrfAvatar", optimizer: torch.optim.Optimizer, step: int, seed: int) -> int:
        return 0  # the occupancy grids are updated in the forward pass (model/occupancy.py)

    def render_view(self, avatar: "SlrfAvatar", state: "NodeState", slot: int, camera: "Camera",
                    background: tuple[float, float, float], max_rays_per_chunk: int,
                    pixel_mask: "np.ndarray | None", progress: "ProgressFn | None") -> "ViewRender":
        from avatarctl.render.engine import march_view

        return march_view(avatar, state, slot, camera, background, max_rays_per_chunk, pixel_mask, progress)


class Rasterized:
    """The structured local Gaussian fields (a deviation, model/gaussian_field.py): K 3D Gaussians per node, posed by
    T_i and n_i, decoded with e_i, rasterized (avatarctl/splat)."""

    name = "gaussians"
    trains_on = "crops"
    splats = True

    def build(self, avatar: "SlrfAvatar", template: "BodyTemplate", rest: torch.Tensor, seed: int,
              off_body: tuple[torch.Tensor, float] | None) -> None:
        from avatarctl.model.gaussian_field import NodeGaussians, initial_gaussians, initial_normals

        cfg = avatar.cfg
        means, log_scales = initial_gaussians(template.vertices, template.faces, rest, cfg.gaussians.per_node,
                                              cfg.support_radius, seed, off_body)
        normals = initial_normals(template.vertices, template.faces,
                                  (means + rest.detach().float().cpu()[:, None]).reshape(-1, 3)
                                  ).reshape(means.shape) if cfg.gaussians.shading == "irradiance" else None
        avatar.fields = NodeGaussians(cfg.gaussians, cfg.num_nodes, cfg.embed_dim, means, log_scales, cfg.sigma,
                                      normals)

    def query(self, avatar: "SlrfAvatar", points: torch.Tensor, dirs: torch.Tensor, point_frame: torch.Tensor,
              state: "NodeState", candidates: tuple[torch.Tensor, torch.Tensor] | None = None
              ) -> tuple[torch.Tensor, torch.Tensor, dict[str, float]]:
        rgb, sigma = avatar._query_gaussians(points, dirs, point_frame, state)
        return rgb, sigma, {"samples": float(points.shape[0]), "valid_samples": float((sigma > 0).sum())}

    def density_control(self, avatar: "SlrfAvatar", optimizer: torch.optim.Optimizer, step: int, seed: int) -> int:
        """Every `gaussians.relocate_every` steps, the dead Gaussians relocated onto live ones (model/densify.py)."""
        g = avatar.cfg.gaussians
        if not g.relocate_every or step % g.relocate_every:
            return 0
        from avatarctl.model.densify import relocate_dead

        return relocate_dead(avatar.fields, optimizer, g.min_opacity, seed, step)

    def render_view(self, avatar: "SlrfAvatar", state: "NodeState", slot: int, camera: "Camera",
                    background: tuple[float, float, float], max_rays_per_chunk: int,
                    pixel_mask: "np.ndarray | None", progress: "ProgressFn | None") -> "ViewRender":
        from avatarctl.render.engine import rasterize_view

        return rasterize_view(avatar, state, slot, camera, background, pixel_mask, progress)


FIELD_KINDS: dict[str, LocalField] = {"mlp": RayMarched(), "gaussians": Rasterized()}


def field_kind(cfg: ModelConfig) -> LocalField:
    """The kind of local field `cfg` describes (`ModelConfig.field`; the LBS baseline's canonical MLP is ray-marched)."""
    return FIELD_KINDS[cfg.field]
