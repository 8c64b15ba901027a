"""`SlrfAvatar`: structured local radiance fields (Zheng et al., CVPR 2022) as one `nn.Module`.

Data flow of one training step (paper Fig. 4):
1. `node_state(cond, mode)`: Eq. 1 node transforms T_i from the body pose; Eq. 8 per-node pose condition; the
   per-node cVAE (Eq. 9-10) gives Delta n_i and e_i; Eq. 3 posed nodes n_i.
2. `render(rays, state, background)`: per ray, near/far from the union of node-influence spheres
   (radius sigma sqrt(-2 ln eps)); 64 uniform samples; for each sample the nodes in range (Eq. 6 weights > 0),
   local coordinates (Eq. 4), local fields F_i (packed per node, supplement Sec. C.2, or dense), fusion (Eq. 5),
   heads (Eq. 7); compositing over the known background (`render/volume.py`).
3. `losses(out, target, state)`: Eq. 11-15.

Variant "lbs_baseline" (Animatable-NeRF-style, pose-only): the same nodes only define a skinning field
omega(p) = sum_i w_i omega_i / sum_i w_i (Animatable NeRF learns a neural blend-weight field instead); a sample is
mapped to canonical space by inverse LBS x_c = T(p)^-1 p with T(p) = sum_j omega_j(p) M_j = sum_i w_i T_i / sum_i w_i,
and one canonical MLP gives the feature. No Delta n, no e, no latent.

Units: metres, world frame of the capture; time stamps t/T in [0, 1]; densities 1/metre; colours in [0, 1].
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import torch
from torch import nn

from avatarctl.body.base import BodyTemplate
from avatarctl.model.config import AUTO, ModelConfig
from avatarctl.model.cvae import MODES, NodeCVAE
from avatarctl.model.deformer import (blending_weights, candidate_pairs, farthest_point_sampling,
                                      local_coordinates_centered, node_pose_attention, node_pose_condition,
                                      node_transforms, pose_attention_map, posed_node_centers, ray_sphere_bounds)
from avatarctl.model.field import BlockPacking, Packing, fuse_features, fuse_features_dense
from avatarctl.model.local_field import field_kind
from avatarctl.model.occupancy import cell_index, occupancy_estimate, select_samples, update_occupancy
from avatarctl.model.losses import (LossTerms, embedding_loss, image_reconstruction_loss, kl_loss,
                                    reconstruction_loss, total_loss, translation_loss)
from avatarctl.geometry.rays import RayBatch
from avatarctl.render.volume import composite, march, uniform_samples

if TYPE_CHECKING:
    from avatarctl.model.gaussian_field import PosedGaussians
    from avatarctl.splat import SplatCamera


TRACK_PULL = 100.0  # lambda_track: weight of L_track (`SlrfAvatar._tracked`), per metre^2 (lambda_pose's scale)


@dataclass
class FrameConditioning:
    """What the model is told about each of the B frames of a batch."""

    joint_transforms: torch.Tensor  # [B, J, 4, 4] M_j(theta) from BodyModel.pose(): canonical -> world
    pose_features: torch.Tensor  # [B, J, 3] local joint rotations (axis-angle), root zeroed
    time: torch.Tensor  # [B] t/T in [0, 1] (normalised time stamp)
    frame_ids: torch.Tensor  # [B] long, index of the training frame (for "per_frame"); -1 for novel poses

    def __post_init__(self) -> None:
        B, J = self.joint_transforms.shape[:2]
        assert self.joint_transforms.shape == (B, J, 4, 4), f"joint_transforms {tuple(self.joint_transforms.shape)}"
        assert self.pose_features.shape == (B, J, 3), f"pose_features: expected [{B}, {J}, 3], got " \
                                                      f"{tuple(self.pose_features.shape)}"
        assert self.time.shape == (B,), f"time: expected [{B}], got {tuple(self.time.shape)}"
        assert self.frame_ids.shape == (B,), f"frame_ids: expected [{B}], got {tuple(self.frame_ids.shape)}"

    def to(self, device: torch.device | str) -> "FrameConditioning":
        return FrameConditioning(self.joint_transforms.to(device), self.pose_features.to(device),
                                 self.time.to(device), self.frame_ids.to(device))


@dataclass
class NodeState:
    """The posed nodes of B frames: everything `render` needs besides the network weights."""

    transforms: torch.Tensor  # [B, N, 4, 4] T_i (Eq. 1)
    centers: torch.Tensor  # [B, N, 3] posed node positions n_i (Eq. 3), world, metres
    delta_n: torch.Tensor  # [B, N, 3] canonical residual translations, metres
    embed: torch.Tensor  # [B, N, E] dynamic detail embeddings
    mu: torch.Tensor | None = None  # [B, N, Z] (None when the encoder did not run)
    logvar: torch.Tensor | None = None  # [B, N, Z]
    pose_penalty: torch.Tensor | None = None  # [] pose-refinement penalty of these frames (None when off)
    track_penalty: torch.Tensor | None = None  # [] tracked nodes: |Eq. 3's n_i - tracked centre|^2 (None: no tracks)
    refine_penalty: torch.Tensor | None = None  # [] their corrections' priors (model/track_refine.py; None: off)

    @property
    def num_frames(self) -> int:
        return self.centers.shape[0]

    def frame(self, slot: int) -> "NodeState":
        """The nodes of frame `slot` alone, a batch of one (transforms, centres, Delta n, e; no cVAE statistics)."""
        one = slice(slot, slot + 1)
        return NodeState(transforms=self.transforms[one], centers=self.centers[one], delta_n=self.delta_n[one],
                         embed=self.embed[one])


@dataclass
class RenderOutputs:
    rgb: torch.Tensor  # [rays, 3] composited over the background
    alpha: torch.Tensor  # [rays] accumulated opacity
    depth: torch.Tensor  # [rays] expected termination distance (metres) given termination; 0 where alpha = 0
    stats: dict[str, float] = field(default_factory=dict)  # pairs, max_node_samples, hit_rays, ...

    @staticmethod
    def cat(outs: list["RenderOutputs"]) -> "RenderOutputs":
        """The outputs of consecutive ray chunks as one (stats summed, "max*" stats maximised)."""
        stats: dict[str, float] = {}
        for o in outs:
            for k, v in o.stats.items():
                stats[k] = max(stats.get(k, 0.0), v) if k.startswith("max") else stats.get(k, 0.0) + v
        return RenderOutputs(rgb=torch.cat([o.rgb for o in outs]), alpha=torch.cat([o.alpha for o in outs]),
                             depth=torch.cat([o.depth for o in outs]), stats=stats)


@dataclass
class ImageOutputs:
    """Rasterized training images (`model.field = "gaussians"`), one per crop of the batch."""

    rgb: list[torch.Tensor]  # [h, w, 3] each, composited over the background
    alpha: list[torch.Tensor]  # [h, w] each
    stats: dict[str, float] = field(default_factory=dict)  # images, gaussians, pixels

    @staticmethod
    def cat(outs: list["ImageOutputs"]) -> "ImageOutputs":
        stats: dict[str, float] = {}
        for o in outs:
            for k, v in o.stats.items():
                stats[k] = v if k == "gaussians" else stats.get(k, 0.0) + v
        return ImageOutputs(rgb=[c for o in outs for c in o.rgb], alpha=[a for o in outs for a in o.alpha],
                            stats=stats)


class SlrfAvatar(nn.Module):
    """The SLRF avatar of one subject. See the module docstring for the data flow."""

    def __init__(self, cfg: ModelConfig, template: BodyTemplate, num_frames: int, seed: int = 0,
                 hull_nodes: tuple[torch.Tensor, torch.Tensor] | None = None,
                 off_body: tuple[torch.Tensor, float] | None = None, cameras: tuple[str, ...] = ()):
        """`hull_nodes` (with `cfg.hull.nodes` = K > 0 or "auto", a deviation: fit/hull_nodes.py): the K off-body
        nodes as (canonical positions [K, 3], nearest template vertex [K]); the other N - K nodes are sampled on the
        surface. None: all N on the surface, the paper's placement (for K > 0 or "auto", placeholders that a
        checkpoint's buffers replace when loading). `off_body` (field "gaussians"): the hull survey's off-body cells
        (canonical points [C, 3], cell side) where the Gaussians of the nodes nearest to them start
        (model/gaussian_field.py `initial_gaussians`). `cameras`: the training cameras' names, in the split's order
        (with `cfg.colour.enabled`: one colour transform each, model/colour.py)."""
        super().__init__()
        V, J = template.skin_weights.shape
        if cfg.num_nodes > V:
            raise ValueError(f"num_nodes={cfg.num_nodes} exceeds the template's {V} vertices")
        K = cfg.hull.nodes
        if hull_nodes is not None:
            if K == AUTO:  # the fit decided K from the masks
                K = int(hull_nodes[0].shape[0])
            if not 0 < K < cfg.num_nodes or hull_nodes[0].shape != (K, 3) or hull_nodes[1].shape != (K,):
                raise ValueError(f"hull_nodes must be ([{K}, 3], [{K}]) with 0 < K < num_nodes for "
                                 f"model.hull.nodes={cfg.hull.nodes!r}, got {tuple(hull_nodes[0].shape)}, "
                                 f"{tuple(hull_nodes[1].shape)}")
        if num_frames < 0 or (cfg.latent == "per_frame" and num_frames < 1):
            raise ValueError(f"num_frames must be >= 0 (>= 1 for latent 'per_frame'), got {num_frames}")
        self.cfg = cfg
        self.num_frames = int(num_frames)
        self.num_joints = J
        weights = template.skin_weights.detach().float()
        if hull_nodes is None:
            idx = farthest_point_sampling(template.vertices, cfg.num_nodes, seed)
            rest = template.vertices.detach().float()[idx]
        else:  # Sec. 3.1's surface sampling for N - K nodes, then the K hull nodes (fit/hull_nodes.py)
            surface = farthest_point_sampling(template.vertices, cfg.num_nodes - K, seed)
            idx = torch.cat([surface, hull_nodes[1].to(surface)])
            rest = torch.cat([template.vertices.detach().float()[surface], hull_nodes[0].float().to(surface.device)])
        # buffers: saved in state_dict, follow .to(device)
        for name in ("track_nodes", "track_rotation", "track_center", "track_pull"):  # garment tracks (`set_tracks`)
            self.register_buffer(name, None)
        self.register_buffer("node_vertex_index", idx.clone())  # [N] long, template vertex of (nearest to) each node
        self.register_buffer("node_rest", rest.clone())  # [N, 3] n_bar_i
        self.register_buffer("node_skin_weights", weights[idx].clone())  # [N, J] omega_i
        self.register_buffer("pose_attention", node_pose_attention(  # [N, J] (W . omega_i), Eq. 8
            weights[idx], pose_attention_map(template.parents, cfg.pose_attention_hops)))
        self.camera_colour = None
        if cfg.colour.enabled and cameras:  # no cameras named (a model built outside a fit): nothing to learn
            from avatarctl.model.colour import CameraColour

            self.camera_colour = CameraColour(cameras)
        self.pose_refine = None
        if cfg.pose_refine.on and num_frames > 0:
            from avatarctl.body.joints import skin_weighted_centroids
            from avatarctl.model.pose_refine import PoseRefinement

            from avatarctl.model.pose_refine import subtree_share

            self.pose_refine = PoseRefinement(num_frames, template.parents, active=subtree_share(
                weights, template.parents) >= cfg.pose_refine.min_share)
            # a rough start; the fit replaces it with centres solved from the training poses (set_centres)
            self.pose_refine.set_centres(skin_weighted_centroids(template.vertices.detach().float(), weights))
        self.track_refine = None  # the tracked garment nodes' per-frame corrections (model/track_refine.py)
        if cfg.track_refine.on and num_frames > 0:
            from avatarctl.model.track_refine import TrackRefinement

            r = cfg.track_refine
            self.track_refine = TrackRefinement(num_frames, cfg.num_nodes, r.lambda_size, r.lambda_smooth,
                                                r.rotation_m)
        if cfg.variant == "slrf":
            self.latent = NodeCVAE(cfg, J, num_frames)
        self.field_kind = field_kind(cfg)  # the local fields' kind: every difference between them (local_field.py)
        self.field_kind.build(self, template, rest, seed, off_body)

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        if prefix + "track_nodes" in state_dict:  # a fit with garment tracks: the buffers take the saved shapes
            centre = state_dict[prefix + "track_center"]
            pull = state_dict.setdefault(prefix + "track_pull", torch.zeros_like(centre))  # older fits: none
            self.set_tracks(state_dict[prefix + "track_nodes"], state_dict[prefix + "track_rotation"], centre, pull)
        # checkpoints written before `occupancy_updates` existed: their grids are past any warm-up
        key = prefix + "occupancy_updates"
        if self.cfg.uses_occupancy and prefix + "occupancy" in state_dict and key not in state_dict:
            state_dict[key] = torch.tensor(self.cfg.occupancy.warmup, dtype=torch.long)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    # ---- step 1: nodes ------------------------------------------------------------------------------------------
    def node_state(self, cond: FrameConditioning, mode: str,
                   generator: torch.Generator | None = None) -> NodeState:
        """Posed nodes and node variables for B frames.

        mode: "posterior" (training: z ~ N(mu, sigma), reparameterised), "mean" (training frames at test: z = mu),
        "zero" (encoder skipped, z = 0), "novel" (novel poses: encoder skipped, z = 0, or with
        `cfg.novel_latent = "train_mean"` the mean of mu over the training frames; model/cvae.py), "sample"
        (z ~ N(0, I) from `generator`).
        """
        if mode not in MODES:
            raise ValueError(f"unknown mode {mode!r}; use one of {MODES}")
        if cond.joint_transforms.shape[1] != self.num_joints:
            raise ValueError(f"conditioning has {cond.joint_transforms.shape[1]} joints, the avatar's template has "
                             f"{self.num_joints}")
        dev, dt = self.node_rest.device, self.node_rest.dtype
        cond = FrameConditioning(cond.joint_transforms.to(dev, dt), cond.pose_features.to(dev, dt),
                                 cond.time.to(dev, dt), cond.frame_ids.to(dev))
        B, N = cond.time.shape[0], self.cfg.num_nodes
        pose_penalty = None
        with _float32_geometry(dev):
            joints = cond.joint_transforms
            if self.pose_refine is not None:  # training frames: refined M'_j (model/pose_refine.py)
                joints = self.pose_refine(joints, cond.frame_ids)
                pose_penalty = self.pose_refine.penalty(cond.frame_ids)
            T = node_transforms(self.node_skin_weights, joints)  # [B, N, 4, 4]  Eq. 1
        mu = logvar = None
        if self.cfg.variant == "slrf":
            theta_i = node_pose_condition(cond.pose_features, self.pose_attention)  # [B, N, 3J]  Eq. 8
            nv = self.latent(theta_i, cond.time, cond.frame_ids, mode, generator)
            delta = nv.delta_n if self.cfg.use_delta_n else torch.zeros_like(nv.delta_n)
            embed = nv.embed if self.cfg.use_embedding else torch.zeros_like(nv.embed)
            mu, logvar = nv.mu, nv.logvar
        else:
            delta = T.new_zeros(B, N, 3)
            embed = T.new_zeros(B, N, self.cfg.embed_dim)
        with _float32_geometry(dev):
            centers = posed_node_centers(T, self.node_rest, delta.to(T.dtype))  # [B, N, 3]  Eq. 3
            track_penalty = refine_penalty = None
            if self.track_nodes is not None:  # training frames: the tracked garment nodes (fit/garment_track.py)
                T, centers, track_penalty, refine_penalty = self._tracked(T, centers, cond.frame_ids)
        return NodeState(transforms=T, centers=centers, delta_n=delta, embed=embed, mu=mu, logvar=logvar,
                         pose_penalty=pose_penalty, track_penalty=track_penalty, refine_penalty=refine_penalty)

    # ---- garment tracks (fit/garment_track.py; a deviation) ------------------------------------------------------
    def set_tracks(self, nodes: torch.Tensor, rotation: torch.Tensor, center: torch.Tensor,
                   pull_offset: torch.Tensor | None = None) -> None:
        """Place the nodes `nodes` [M] on training frame f at the tracked linear part rotation[f] [M, 3, 3] and centre
        center[f] [M, 3] (world) instead of T_i's skinned linear part and Eq. 3's n_i: T_i = [R | c - R n_bar_i], so
        n_i = c; their Delta n is pulled there instead (L_track, `_tracked`; to c + pull_offset[f] [M, 3] where given:
        the rescued frames' placement without the rescue, fit/garment_track.py step 2b) and places them on novel
        poses (frame_ids -1: the paper's placement). Saved with the weights (buffers)."""
        F = self.num_frames
        M = int(nodes.shape[0])
        pull_offset = torch.zeros_like(center) if pull_offset is None else pull_offset
        if rotation.shape != (F, M, 3, 3) or center.shape != (F, M, 3) or pull_offset.shape != (F, M, 3):
            raise ValueError(f"tracks for {F} frames and {M} nodes: rotation {tuple(rotation.shape)}, "
                             f"center {tuple(center.shape)}, pull_offset {tuple(pull_offset.shape)}")
        dev = self.node_rest.device
        for name, value in (("track_nodes", nodes.long()), ("track_rotation", rotation.float()),
                            ("track_center", center.float()), ("track_pull", pull_offset.float())):
            self._buffers[name] = value.to(dev).clone()

    def _tracked(self, T: torch.Tensor, centers: torch.Tensor, frame_ids: torch.Tensor
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
        """-> (T, centers) with the tracked nodes placed on training frames, L_track: the mean over those frames of
        sum over the tracked nodes of |n_i - c_i|^2 (Eq. 3's centre with its Delta n against the tracked centre,
        metres^2), so that Delta n learns the tracked placement and predicts it on novel poses, and the priors of
        the placement's per-frame corrections (`track_refine`, model/track_refine.py: c_i and R_i corrected first;
        None when off). Both None: no training frame here. In training, each frame keeps the paper's placement with
        probability `cfg.track_free` (the global RNG): the garment is drawn from where Delta n puts it there too, as
        on novel poses."""
        train = (frame_ids >= 0).nonzero(as_tuple=True)[0]
        if not train.numel():
            return T, centers, None, None
        nodes, f = self.track_nodes, frame_ids[train]
        c = self.track_center[f].to(T.dtype)  # [b, M, 3]
        R = self.track_rotation[f].to(T.dtype)  # [b, M, 3, 3]
        refine_penalty = None
        if self.track_refine is not None:
            R, c = self.track_refine(R, c, f, nodes)
            refine_penalty = self.track_refine.penalty(f, nodes)
        pull = c.detach() + self.track_pull[f].to(T.dtype)
        penalty = ((centers[train][:, nodes] - pull) ** 2).sum(dim=(-2, -1)).mean()
        if self.training and self.cfg.track_free > 0:  # a share of the frames placed the paper's way this step
            keep = (torch.rand(train.numel()) >= self.cfg.track_free).to(train.device)
            if not keep.any():
                return T, centers, penalty, refine_penalty
            train, c, R = train[keep], c[keep], R[keep]
        T, centers = T.clone(), centers.clone()
        b = train[:, None]
        T[b, nodes[None], :3, :3] = R
        T[b, nodes[None], :3, 3] = c - (R @ self.node_rest[nodes].to(T.dtype)[None, ..., None])[..., 0]
        centers[b, nodes[None]] = c
        return T, centers, penalty, refine_penalty

    def set_latent_mean(self, cond: FrameConditioning) -> None:
        """With `cfg.novel_latent = "train_mean"`: store the mean posterior mean of the cVAE over `cond`'s frames (all
        training frames) as the novel-pose latent (model/cvae.py). A no-op otherwise."""
        if self.cfg.variant != "slrf" or not hasattr(self.latent, "latent_mean"):
            return
        dev, dt = self.node_rest.device, self.node_rest.dtype
        theta_i = node_pose_condition(cond.pose_features.to(dev, dt), self.pose_attention)  # [T, N, 3J]  Eq. 8
        self.latent.set_latent_mean(theta_i, cond.time.to(dev, dt), cond.frame_ids.to(dev))

    def knock_out(self, state: NodeState, delta_n: bool = False, embedding: bool = False) -> NodeState:
        """`state` with Delta n_i and/or e_i set to zero at render time (the paper's render-time knockout of a
        trained model, Fig. 3 / supp. Tab. B): the nodes move back to their skinned positions (Eq. 3 with Delta n = 0)."""
        delta = torch.zeros_like(state.delta_n) if delta_n else state.delta_n
        embed = torch.zeros_like(state.embed) if embedding else state.embed
        with _float32_geometry(state.transforms.device):
            centers = posed_node_centers(state.transforms, self.node_rest, delta.to(state.transforms.dtype))
        return NodeState(transforms=state.transforms, centers=centers, delta_n=delta, embed=embed, mu=state.mu,
                         logvar=state.logvar)

    # ---- step 2 (field "gaussians"): rasterizing ------------------------------------------------------------------
    def posed_gaussians(self, state: NodeState) -> "PosedGaussians":
        """The Gaussians of every frame of `state`, posed by T_i, n_i and decoded with e_i (model/gaussian_field.py)."""
        if not self.field_kind.splats:
            raise ValueError(f"posed_gaussians needs model.field = 'gaussians', this avatar's is {self.cfg.field!r}")
        with _float32_geometry(state.transforms.device):
            return self.fields(state.transforms, state.centers, state.embed)

    def render_image(self, posed: "PosedGaussians", slot: int, camera: "SplatCamera", background: torch.Tensor,
                     backend: str = "auto") -> tuple[torch.Tensor, torch.Tensor]:
        """Rasterize frame `slot` of `posed` seen by `camera` (`splat.rasterization`, a batch of one) over
        `background` [3] -> rgb [H, W, 3], alpha [H, W]."""
        from avatarctl.splat import rasterization

        colors = posed.colors(slot, camera.center)
        rgb, alpha, _ = rasterization(posed.means[slot], posed.covars[slot], colors, posed.opacities[slot], [camera],
                                      background.to(colors), backend=backend, low_pass=self.cfg.gaussians.low_pass)
        return rgb[0], alpha[0]

    def render_images(self, posed: "PosedGaussians", cameras: list["SplatCamera"], background: torch.Tensor,
                      backend: str = "auto") -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        """Rasterize frame slot b of `posed` seen by cameras[b], for every b at once (`splat.rasterization`: one
        projection, one binning, one launch) -> rgb [[H_b, W_b, 3]], alpha [[H_b, W_b]]."""
        from avatarctl.splat import rasterization

        B = len(cameras)
        assert B == posed.means.shape[0], f"render_images: {B} cameras for {posed.means.shape[0]} frame slots"
        centers = torch.stack([c.center for c in cameras])
        colors = posed.colors_batch(list(range(B)), centers)
        rgb, alpha, _ = rasterization(posed.means, posed.covars, colors, posed.opacities, cameras,
                                      background.to(colors), backend=backend, low_pass=self.cfg.gaussians.low_pass)
        return list(rgb), list(alpha)

    def image_losses(self, rgb: list[torch.Tensor], alpha: list[torch.Tensor], target: list[torch.Tensor],
                     mask: list[torch.Tensor], state: NodeState) -> LossTerms:
        """Eq. 11 with the image loss of the rasterized field in place of Eq. 12 (`losses.image_reconstruction_loss`:
        L1 + D-SSIM + mask, per image crop) and the paper's regularisers (Eq. 13-15) as in `losses`."""
        c, g = self.cfg, self.cfg.gaussians
        rec, mse = image_reconstruction_loss(rgb, target, alpha, mask, g.lambda_ssim, g.lambda_mask,
                                             c.rec_reference_rays, border_px=g.border_px)
        return self._with_regularisers(rec, mse, state)

    # ---- step 2: rendering --------------------------------------------------------------------------------------
    def render(self, rays: RayBatch, state: NodeState, background: torch.Tensor, *, jitter: bool = False,
               generator: torch.Generator | None = None, chunk: int | None = None) -> RenderOutputs:
        """Volume-render `rays` (each against the nodes of its frame slot) over `background` [3].

        Rays that miss every node sphere return the background with alpha 0. `chunk` bounds memory (rays per chunk).
        """
        if self.field_kind.trains_on != "rays":
            raise ValueError("model.field 'gaussians' is rasterized, not ray-marched: use render_image")
        dev, dt = self.node_rest.device, self.node_rest.dtype
        rays = RayBatch(rays.origins.to(dev, dt), rays.dirs.to(dev, dt), rays.frame_slot.to(dev))
        bg = torch.as_tensor(background, device=dev, dtype=dt).reshape(3)
        if len(rays) and int(rays.frame_slot.max()) >= state.num_frames:
            raise ValueError(f"frame_slot {int(rays.frame_slot.max())} out of range for {state.num_frames} frames")
        if chunk is None or len(rays) <= chunk:
            return self._render_rays(rays, state, bg, jitter, generator)
        return RenderOutputs.cat([self._render_rays(rays.select(slice(s, s + chunk)), state, bg, jitter, generator)
                                  for s in range(0, len(rays), chunk)])

    def _render_rays(self, rays: RayBatch, state: NodeState, bg: torch.Tensor, jitter: bool,
                     generator: torch.Generator | None) -> RenderOutputs:
        R, S = len(rays), self.cfg.samples_per_ray
        near, far, hit = ray_sphere_bounds(rays.origins, rays.dirs, state.centers[rays.frame_slot].detach(),
                                           self.cfg.support_radius)
        hit_idx = hit.nonzero(as_tuple=True)[0]
        stats = {"rays": float(R), "hit_rays": float(hit_idx.numel()), "samples": 0.0, "valid_samples": 0.0,
                 "pairs": 0.0, "packed_slots": 0.0, "max_node_samples": 0.0}
        rgb = bg.expand(R, 3)
        alpha = bg.new_zeros(R)
        depth = bg.new_zeros(R)
        if hit_idx.numel() == 0:
            return RenderOutputs(rgb=rgb.clone(), alpha=alpha, depth=depth, stats=stats)
        frame_pts = rays.frame_slot[hit_idx][:, None].expand(-1, S).reshape(-1)  # [hit * S]
        if self.cfg.occupancy.enabled and self.cfg.sparse:
            rgb_h, alpha_h, depth_h = self._march_occupied(rays, hit_idx, near, far, frame_pts, state, bg, jitter,
                                                           generator, stats)
            return RenderOutputs(rgb=rgb.index_copy(0, hit_idx, rgb_h), alpha=alpha.index_copy(0, hit_idx, alpha_h),
                                 depth=depth.index_copy(0, hit_idx, depth_h), stats=stats)

        def field_fn(pts: torch.Tensor, dirs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            c, s, st = self.query(pts.reshape(-1, 3), dirs.reshape(-1, 3), frame_pts, state)
            stats.update(st)
            return c.reshape(*pts.shape[:2], 3), s.reshape(pts.shape[:2])

        comp = march(field_fn, rays.origins[hit_idx], rays.dirs[hit_idx], near[hit_idx], far[hit_idx], S, bg,
                     jitter, generator)
        return RenderOutputs(rgb=rgb.index_copy(0, hit_idx, comp.rgb), alpha=alpha.index_copy(0, hit_idx, comp.alpha),
                             depth=depth.index_copy(0, hit_idx, comp.depth), stats=stats)

    def _march_occupied(self, rays: RayBatch, hit_idx: torch.Tensor, near: torch.Tensor, far: torch.Tensor,
                        frame_pts: torch.Tensor, state: NodeState, bg: torch.Tensor, jitter: bool,
                        generator: torch.Generator | None, stats: dict[str, float]):
        """`march` with empty-space skipping (model/occupancy.py): the same samples, but the field runs only at the
        samples the occupancy grids call live (plus, in training, a random `occupancy.explore` share of the others);
        skipped samples have density 0. -> rgb [hit, 3], alpha [hit], depth [hit]."""
        occ, S = self.cfg.occupancy, self.cfg.samples_per_ray
        o, d = rays.origins[hit_idx], rays.dirs[hit_idx]
        t = uniform_samples(near[hit_idx], far[hit_idx], S, jitter, generator)  # [hit, S]
        pts = (o[:, None, :] + t[..., None] * d[:, None, :]).reshape(-1, 3)  # [hit * S, 3]
        with torch.no_grad():
            pi, ni, fi, _, centers = self._pairs(pts, frame_pts, state)
            cells = cell_index(self._local(pts, pi, ni, fi, centers, state), ni,
                               self._node_extent(), occ.res)
            dens, unseen = occupancy_estimate(self.occupancy, cells, pi, pts.shape[0])
            live = select_samples(dens.reshape(t.shape), unseen.reshape(t.shape), occ.threshold).reshape(-1)
            if self.training and int(self.occupancy_updates) < occ.warmup:
                live = torch.ones_like(live)  # warm-up: evaluate everything while the grids fill
            elif self.training and occ.explore > 0:
                dev = generator.device if generator is not None else pts.device
                live |= (torch.rand(live.shape[0], generator=generator, device=dev) < occ.explore).to(pts.device)
            keep = live[pi]  # the live samples' pairs, renumbered: query need not search them again
            candidates = ((torch.cumsum(live, 0) - 1)[pi[keep]], ni[keep])
        idx = live.nonzero(as_tuple=True)[0]
        rgb = pts.new_zeros(pts.shape[0], 3)
        sigma = pts.new_zeros(pts.shape[0])
        if idx.numel():
            dirs = d[:, None, :].expand(-1, S, -1).reshape(-1, 3)
            c, sg, st = self.query(pts[idx], dirs[idx], frame_pts[idx], state, candidates)
            stats.update(st)
            rgb, sigma = rgb.index_copy(0, idx, c), sigma.index_copy(0, idx, sg)
        stats["samples"] = float(pts.shape[0])
        stats["live_samples"] = float(idx.numel())
        rgb, sigma = rgb.reshape(*t.shape, 3), sigma.reshape(t.shape)
        out, alpha, depth, _ = composite(rgb, sigma, t, bg)
        return out, alpha, depth

    def query(self, points: torch.Tensor, dirs: torch.Tensor, point_frame: torch.Tensor, state: NodeState,
              candidates: tuple[torch.Tensor, torch.Tensor] | None = None
              ) -> tuple[torch.Tensor, torch.Tensor, dict[str, float]]:
        """Colour and density at posed points.

        points [P, 3] world, dirs [P, 3] unit viewing directions, point_frame [P] long (frame slot of each point)
        -> rgb [P, 3], sigma [P] (1/metre; exactly 0 where no node is in range), stats. In training with
        `cfg.occupancy.enabled`, the densities found update the occupancy grids (model/occupancy.py). `candidates`
        (point_idx, node_idx) [pairs]: the pairs in range, already found (sparse path only).
        """
        return self.field_kind.query(self, points, dirs, point_frame, state, candidates)

    def _query_heads(self, points: torch.Tensor, dirs: torch.Tensor, point_frame: torch.Tensor, state: NodeState,
                     candidates: tuple[torch.Tensor, torch.Tensor] | None = None
                     ) -> tuple[torch.Tensor, torch.Tensor, dict[str, float]]:
        """`query` of the ray-marched fields: the fused feature of the nodes in range (Eq. 5), then the heads (Eq. 7)."""
        if self.cfg.sparse:
            f, wsum, stats, occ_pairs = self._features_sparse(points, point_frame, state, candidates)
            valid = (wsum > 0).nonzero(as_tuple=True)[0]
            fv = f[valid]
            # heads may run in bf16 under autocast; compositing stays in the points' float32
            sigma = points.new_zeros(points.shape[0]).index_copy(0, valid, self.heads.density(fv).to(points.dtype))
            rgb = points.new_zeros(points.shape[0], 3).index_copy(0, valid,
                                                                  self.heads.color(fv, dirs[valid]).to(points.dtype))
            if occ_pairs is not None and self.training and torch.is_grad_enabled():
                update_occupancy(self.occupancy, occ_pairs[1], sigma.detach()[occ_pairs[0]], self.cfg.occupancy.decay)
                self.occupancy_updates += 1
        else:
            f, wsum, stats = self._features_dense(points, point_frame, state)
            valid_mask = wsum > 0
            valid = valid_mask.nonzero(as_tuple=True)[0]
            sigma = torch.where(valid_mask, self.heads.density(f), torch.zeros_like(wsum))
            rgb = torch.where(valid_mask[:, None], self.heads.color(f, dirs), torch.zeros_like(f[:, :3]))
        stats["samples"] = float(points.shape[0])
        stats["valid_samples"] = float(valid.numel())
        return rgb, sigma, stats

    def _query_gaussians(self, points: torch.Tensor, dirs: torch.Tensor, point_frame: torch.Tensor,
                         state: NodeState) -> tuple[torch.Tensor, torch.Tensor]:
        """`query` of the Gaussian local fields (mesh export; no gradients): the Gaussians as a density
        (`splat.density`: each within 4 of its Mahalanobis radii), sigma(x) = sum_g tau_g exp(-d^T Sigma_g^-1 d / 2) /
        (sqrt(2 pi) s_g), s_g = det(Sigma_g)^(1/6) (1/metre), tau_g = -ln(1 - min(o_g, 0.99)): a ray through an
        isotropic Gaussian's centre accumulates the optical depth tau_g, i.e. the opacity 1 - exp(-tau_g) = o_g that
        the rasterizer gives the splat's centre (before 2026-11-27 tau_g was o_g, so an opaque splat let 37 %
        through: exported meshes of Gaussian avatars came out dark), and the colour as the sum of the Gaussians'
        view-dependent colours (SH at the direction in their node's frame) weighted by their terms.
        points / dirs [P, 3], point_frame [P] -> rgb [P, 3], sigma [P]."""
        from avatarctl.splat.density import gaussian_field_at

        posed = self.posed_gaussians(state)
        K = posed.per_node
        depth = -torch.log1p(-posed.opacities.clamp(max=0.99))  # tau_g: optical depth through the centre
        norm = depth / (math.sqrt(2 * math.pi) * torch.linalg.det(posed.covars).clamp(min=1e-30) ** (1 / 6))
        sigma = points.new_zeros(points.shape[0])
        rgb = points.new_zeros(points.shape[0], 3)
        for f in torch.unique(point_frame).tolist():
            idx = (point_frame == f).nonzero(as_tuple=True)[0]
            maps = posed.linear_inv[f].repeat_interleave(K, 0) if posed.sh.shape[2] > 1 else None  # [G, 3, 3]
            c, s = gaussian_field_at(points[idx], dirs[idx], posed.means[f], posed.covars[f], norm[f], posed.sh[f],
                                     maps)
            rgb[idx], sigma[idx] = c.to(rgb), s.to(sigma)
        return rgb, sigma

    def _local_scale(self) -> float:
        """Local coordinates are in units of sigma (module docstring of model/config.py)."""
        return 1.0 / self.cfg.sigma

    def _node_extent(self) -> float:
        """Half side of a node's support cube in local-coordinate units (grid fields and occupancy grids)."""
        return self.cfg.support_radius * self._local_scale()

    def _pairs(self, points: torch.Tensor, point_frame: torch.Tensor, state: NodeState,
               candidates: tuple[torch.Tensor, torch.Tensor] | None = None):
        """The (point, node) pairs with Eq. 6 weight > 0: point_idx, node_idx, frame_idx [pairs] long, w [pairs],
        centers [pairs, 3] (the posed node of each pair). `candidates`: (point_idx, node_idx) found before, in the
        order `candidate_pairs` gives, instead of a new neighbour search."""
        cfg = self.cfg
        pi, ni = candidates if candidates is not None else candidate_pairs(points, point_frame, state.centers,
                                                                             cfg.support_radius)
        fi = point_frame[pi]
        centers = state.centers[fi, ni]  # [pairs, 3]
        w = blending_weights(((points[pi] - centers) ** 2).sum(-1), cfg.sigma, cfg.eps)  # Eq. 6
        keep = (w > 0).nonzero(as_tuple=True)[0]
        return pi[keep], ni[keep], fi[keep], w[keep], centers[keep]

    def _local(self, points: torch.Tensor, pi: torch.Tensor, ni: torch.Tensor, fi: torch.Tensor,
               centers: torch.Tensor, state: NodeState) -> torch.Tensor:
        """Eq. 4 local coordinates of each pair [pairs, 3], in units of sigma."""
        with _float32_geometry(points.device):
            A_inv = torch.linalg.inv(state.transforms[..., :3, :3])  # [B, N, 3, 3]
            return local_coordinates_centered(points[pi], A_inv[fi, ni], centers) * self._local_scale()

    def _features_sparse(self, points: torch.Tensor, point_frame: torch.Tensor, state: NodeState,
                         candidates: tuple[torch.Tensor, torch.Tensor] | None = None):
        """Supplement Sec. C.2: evaluate only pairs with w_i > 0, packed per node ([N, max_i S_i, C], or blocks of
        `cfg.pack_block` rows per node, see `ModelConfig.pack_block`).
        -> f [P, F], wsum [P], stats, and with `cfg.occupancy.enabled` (point_idx, cells) of the pairs, else None."""
        cfg, N, P = self.cfg, self.cfg.num_nodes, points.shape[0]
        pi, ni, fi, w, centers = self._pairs(points, point_frame, state, candidates)
        on_nodes = cfg.variant == "slrf" or cfg.occupancy.enabled
        local = self._local(points, pi, ni, fi, centers, state) if on_nodes else None
        occ_pairs = None
        if cfg.occupancy.enabled:
            occ_pairs = (pi, cell_index(local, ni, self._node_extent(), cfg.occupancy.res))
        if cfg.variant == "slrf":
            if cfg.pack_block > 0:
                bp = BlockPacking.build(ni, N, cfg.pack_block)
                o = bp.order
                bias = self.fields.embed_bias(state.embed)[fi[o], ni[o]]  # [pairs, width] W_e e_i of each pair
                feats = bp.unpack(self.fields(bp.pack(local[o]), bp.pack(bias), node_index=bp.block_node))
                f, wsum = fuse_features(feats, w[o], pi[o], P)  # Eq. 5
                width, slots = cfg.pack_block, bp.num_blocks * cfg.pack_block
            else:
                pk = Packing.build(ni, N)
                # the large per-pair tensors live only in the packed layout [N, S', C]; padding has w = 0, point P
                frame_p = pk.pack_index(fi, N, fill=0)  # [N, S']
                point_p = pk.pack_index(pi, N, fill=P)  # [N, S'], P = a dummy point dropped below
                w_p = pk.pack(w[:, None], N)[..., 0]  # [N, S']
                ebias = self.fields.embed_bias(state.embed).transpose(0, 1)  # [N, B, width]
                onehot = torch.nn.functional.one_hot(frame_p, ebias.shape[1]).to(ebias.dtype)  # [N, S', B]
                bias_p = torch.bmm(onehot, ebias)  # [N, S', width] = ebias[node, frame] (a gather as a matmul)
                feats_p = self.fields(pk.pack(local, N), bias_p)  # [N, S', F]
                f, wsum = fuse_features(feats_p.flatten(0, 1), w_p.flatten(), point_p.flatten(), P + 1)  # Eq. 5
                f, wsum = f[:P], wsum[:P]
                width, slots = pk.width, N * pk.width
        else:
            wsum = w.new_zeros(P).index_add(0, pi, w)
            Tp = w.new_zeros(P, 4, 4).index_add(0, pi, w[:, None, None] * state.transforms[fi, ni])
            f = self._canonical_features(points, Tp, wsum)
            width = slots = 0
        stats = {"pairs": float(pi.numel()), "packed_slots": float(slots), "max_node_samples": float(width)}
        return f, wsum, stats, occ_pairs

    def _features_dense(self, points: torch.Tensor, point_frame: torch.Tensor,
                        state: NodeState) -> tuple[torch.Tensor, torch.Tensor, dict[str, float]]:
        """Reference path: every node for every sample ([N, P, C] tensors)."""
        cfg, N, P = self.cfg, self.cfg.num_nodes, points.shape[0]
        centers = state.centers[point_frame].transpose(0, 1)  # [N, P, 3]
        w = blending_weights(((points[None] - centers) ** 2).sum(-1), cfg.sigma, cfg.eps)  # [N, P]  Eq. 6
        if cfg.variant == "slrf":
            with _float32_geometry(points.device):
                A_inv = torch.linalg.inv(state.transforms[..., :3, :3])[point_frame].transpose(0, 1)  # [N, P, 3, 3]
                local = local_coordinates_centered(points[None], A_inv, centers) * self._local_scale()  # Eq. 4
            bias = self.fields.embed_bias(state.embed)[point_frame].transpose(0, 1)  # [N, P, width]
            f, wsum = fuse_features_dense(self.fields(local, bias), w)  # Eq. 5
        else:
            wsum = w.sum(0)
            Tp = torch.einsum("np,npab->pab", w, state.transforms[point_frame].transpose(0, 1))
            f = self._canonical_features(points, Tp, wsum)
        stats = {"pairs": float(N * P), "packed_slots": float(N * P), "max_node_samples": float(P)}
        return f, wsum, stats

    def _canonical_features(self, points: torch.Tensor, Tp_unnormalised: torch.Tensor,
                            wsum: torch.Tensor) -> torch.Tensor:
        """lbs_baseline: x_c = T(p)^-1 p with T(p) = sum_i w_i T_i / sum_i w_i; features of the valid points only."""
        valid = (wsum > 0).nonzero(as_tuple=True)[0]
        Tv = Tp_unnormalised[valid] / wsum[valid][:, None, None]
        xc = torch.linalg.solve(Tv[:, :3, :3], (points[valid] - Tv[:, :3, 3])[..., None]).squeeze(-1)
        fv = self.canonical(xc)
        return fv.new_zeros(points.shape[0], fv.shape[-1]).index_copy(0, valid, fv)

    # ---- step 3: losses -----------------------------------------------------------------------------------------
    def losses(self, out: RenderOutputs, target_rgb: torch.Tensor, state: NodeState) -> LossTerms:
        """Eq. 11-15 (reductions in `model/losses.py`). target_rgb [rays, 3] in [0, 1]."""
        c = self.cfg
        target = target_rgb.to(out.rgb.device)
        rec = reconstruction_loss(out.rgb, target, c.rec_reduction, c.rec_reference_rays)
        mse = rec if c.rec_reduction == "mean" else reconstruction_loss(out.rgb.detach(), target, "mean")
        return self._with_regularisers(rec, mse, state)

    def _with_regularisers(self, rec: torch.Tensor, mse: torch.Tensor, state: NodeState) -> LossTerms:
        """Eq. 11: the reconstruction term plus Eq. 13-15 (and the pose-refinement and camera-colour terms when
        on)."""
        c, refine = self.cfg, self.cfg.pose_refine
        zero = rec.new_zeros(())
        kl = kl_loss(state.mu, state.logvar) if state.mu is not None and state.logvar is not None else zero
        colour = self.camera_colour.penalty() if self.camera_colour is not None else None
        return total_loss(rec, translation_loss(state.delta_n), embedding_loss(state.embed), kl,
                          c.lambda_rec, c.lambda_trans, c.lambda_ebd, c.lambda_kl, mse=mse,
                          pose=state.pose_penalty, lambda_pose=refine.lambda_pose, colour=colour,
                          lambda_colour=c.colour.lambda_identity, track=state.track_penalty,
                          lambda_track=TRACK_PULL, refine=state.refine_penalty)


def _float32_geometry(device: torch.device):
    """Autocast off: node transforms, their inverses and local coordinates stay float32 under bf16 mixed precision
    (`linalg.inv` has no bf16 kernel, and bf16 coordinates would put ~0.5 rad of phase error on the highest
    positional-encoding frequency). Only the MLPs run in bf16."""
    return torch.autocast(device_type=device.type, enabled=False)
