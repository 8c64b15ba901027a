"""One training step's forward pass and loss, for each kind of data a local field trains on.

The model's kind of local field (`model.local_field.LocalField.trains_on`) says what its step's batch holds; `STEPS`
maps that to the `TrainingSteps` here, which draws the batches (its sampler, fit/data.py) and computes the loss of
Eq. 11 over this rank's shards (fit/distributed.py `Replicas` calls `forward`):

- `RaySteps` ("rays", the ray-marched fields): scattered rays per image, volume-rendered, Eq. 12 per ray. Several
  shards on one rank are rendered as their own ranks would (each from the occupancy grid of the step's start), then
  concatenated, the grids merged as across ranks (`distributed.merge_occupancy`).
- `CropSteps` ("crops", the Gaussian local fields): whole image crops, rasterized, L1 + D-SSIM + mask per crop.

Each returns (loss terms, outputs, rays or pixels of the whole step over all ranks).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol

import torch

from avatarctl.fit.data import FrameStore, ImageBatch, ImageSampler, PairSampler, RaySampler, TrainBatch
from avatarctl.model.config import ModelConfig
from avatarctl.model.local_field import field_kind

if TYPE_CHECKING:
    from avatarctl.fit.config import FitConfig
    from avatarctl.model.avatar import ImageOutputs, NodeState, RenderOutputs, SlrfAvatar
    from avatarctl.model.losses import LossTerms


class TrainingSteps(Protocol):
    """The batches of one kind of training data and the step's forward pass over them."""

    def sampler(self, store: FrameStore, cfg: "FitConfig", train_frames: list[int], train_views: list[str],
                pairs: list[tuple[int, str]] | None, rays: int, images: int) -> PairSampler:
        """A sampler of `images` images (and `rays` rays) per step from `pairs` (None: every training pair)."""
        ...

    def forward(self, model: "SlrfAvatar", parts: list, background: torch.Tensor, jitter: bool,
                noise_gens: dict[int, torch.Generator], world: int) -> tuple["LossTerms", object, int]:
        """parts: [(shard, batch)] of this rank -> (loss terms, outputs, rays or pixels over all `world` ranks)."""
        ...


class RaySteps:
    """Scattered rays, volume-rendered (the ray-marched fields)."""

    def sampler(self, store: FrameStore, cfg: "FitConfig", train_frames: list[int], train_views: list[str],
                pairs: list[tuple[int, str]] | None, rays: int, images: int) -> RaySampler:
        return RaySampler(store, train_frames, train_views, rays, images, cfg.box_fraction, cfg.background,
                          pairs)

    def forward(self, model: "SlrfAvatar", parts: list[tuple[int, TrainBatch]], background: torch.Tensor,
                jitter: bool, noise_gens: dict[int, torch.Generator], world: int
                ) -> tuple["LossTerms", "RenderOutputs", int]:
        if len(parts) == 1:
            k, b = parts[0]
            state = model.node_state(b.cond, mode="posterior", generator=noise_gens[k])
            out = model.render(b.rays, state, background, jitter=jitter, generator=noise_gens[k])
            out = camera_colour_rays(model, out, b, background)
            return model.losses(out, b.target, state), out, b.target.shape[0] * world
        state, out, target = self._shards(model, parts, background, jitter, noise_gens)
        return model.losses(out, target, state), out, target.shape[0] * world

    @staticmethod
    def _shards(model: "SlrfAvatar", parts: list[tuple[int, TrainBatch]], background: torch.Tensor, jitter: bool,
                noise_gens: dict[int, torch.Generator]) -> tuple["NodeState", "RenderOutputs", torch.Tensor]:
        """Several shards on this rank: each rendered as its own rank would (its noise generator, the occupancy grid
        of the step's start), then concatenated; the grids merged as across ranks."""
        from avatarctl.fit.distributed import cat_states, merge_occupancy
        from avatarctl.model.avatar import RenderOutputs

        occ = getattr(model, "occupancy", None) if model.cfg.uses_occupancy else None
        start = (occ.clone(), model.occupancy_updates.clone()) if occ is not None else None
        states, outs, afters = [], [], []
        for k, b in parts:
            if start is not None:
                model.occupancy.copy_(start[0])
                model.occupancy_updates.copy_(start[1])
            st = model.node_state(b.cond, mode="posterior", generator=noise_gens[k])
            states.append(st)
            outs.append(camera_colour_rays(model, model.render(b.rays, st, background, jitter=jitter,
                                                               generator=noise_gens[k]), b, background))
            if start is not None:
                afters.append(model.occupancy.clone())
        if start is not None:
            model.occupancy.copy_(merge_occupancy(start[0], afters))
        counts = [int((b.cond.frame_ids >= 0).sum()) for _, b in parts]
        return cat_states(states, counts), RenderOutputs.cat(outs), torch.cat([b.target for _, b in parts])


class CropSteps:
    """Whole image crops, rasterized (the Gaussian local fields)."""

    def sampler(self, store: FrameStore, cfg: "FitConfig", train_frames: list[int], train_views: list[str],
                pairs: list[tuple[int, str]] | None, rays: int, images: int) -> ImageSampler:
        return ImageSampler(store, train_frames, train_views, images, cfg.background, pairs)

    def forward(self, model: "SlrfAvatar", parts: list[tuple[int, ImageBatch]], background: torch.Tensor,
                jitter: bool, noise_gens: dict[int, torch.Generator], world: int
                ) -> tuple["LossTerms", "ImageOutputs", int]:
        """Each shard's node state (its noise generator), its crops rasterized, the image loss over all of this
        rank's crops."""
        from avatarctl.fit.distributed import cat_states
        from avatarctl.model.avatar import ImageOutputs

        states, outs, counts = [], [], []
        for k, b in parts:
            st = model.node_state(b.cond, mode="posterior", generator=noise_gens[k])
            states.append(st)
            outs.append(camera_colour_crops(model, render_crops(model, b, st, background), b, background))
            counts.append(int((b.cond.frame_ids >= 0).sum()))
        state = states[0] if len(states) == 1 else cat_states(states, counts)
        out = ImageOutputs.cat(outs)
        batches = [b for _, b in parts]
        targets = [c.target for b in batches for c in b.crops]
        masks = [c.mask for b in batches for c in b.crops]
        terms = model.image_losses(out.rgb, out.alpha, targets, masks, state)
        return terms, out, sum(b.pixels for b in batches) * world


def render_crops(model: "SlrfAvatar", batch: ImageBatch, state: "NodeState", background: torch.Tensor
                 ) -> "ImageOutputs":
    """Rasterize every crop of `batch` (crop b is frame slot b of `state`) with the avatar's posed Gaussians."""
    from avatarctl.model.avatar import ImageOutputs
    from avatarctl.splat import SplatCamera

    posed = model.posed_gaussians(state)
    cams = [SplatCamera.from_camera(c.camera, device=c.target.device).crop(c.x0, c.y0, c.mask.shape[1], c.mask.shape[0])
            for c in batch.crops]
    rgb, alpha = model.render_images(posed, cams, background)
    return ImageOutputs(rgb=rgb, alpha=alpha, stats={"images": float(len(rgb)), "gaussians": float(
        posed.means.shape[1]), "pixels": float(batch.pixels)})


def camera_colour_rays(model: "SlrfAvatar", out: "RenderOutputs", batch: "TrainBatch", background: torch.Tensor
                       ) -> "RenderOutputs":
    """The rays of `batch` as their cameras see them: each ray's render through its training camera's colour transform
    (model/colour.py; `model.colour.enabled`), before the loss. Unchanged when the transforms are off."""
    colour = model.camera_colour
    if colour is None:
        return out
    from dataclasses import replace

    cams = colour.index(batch.views, out.rgb.device)[batch.rays.frame_slot.to(out.rgb.device)]  # [rays]
    return replace(out, rgb=colour(out.rgb, out.alpha, background.to(out.rgb.device), cams))


def camera_colour_crops(model: "SlrfAvatar", out: "ImageOutputs", batch: "ImageBatch", background: torch.Tensor
                        ) -> "ImageOutputs":
    """The rasterized crops of `batch` as their cameras see them (`camera_colour_rays` for whole crops)."""
    colour = model.camera_colour
    if colour is None:
        return out
    from dataclasses import replace

    cams = colour.index(batch.views)
    rgb = [colour(c, a, background.to(c.device), cams[b].to(c.device).expand(a.shape))
           for b, (c, a) in enumerate(zip(out.rgb, out.alpha))]
    return replace(out, rgb=rgb)


STEPS: dict[str, TrainingSteps] = {"rays": RaySteps(), "crops": CropSteps()}


def training_steps(cfg: ModelConfig) -> TrainingSteps:
    """The training steps of the local fields `cfg` describes (their kind's `trains_on`)."""
    return STEPS[field_kind(cfg).trains_on]
