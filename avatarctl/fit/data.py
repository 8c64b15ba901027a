"""Training data: a RAM-bounded LRU store of cropped frames, the ray sampler and the image-crop sampler.

Frames are read lazily from the project (`ProjectCapture.image / mask`), cropped to the projection of the posed
body's 3D bounding box grown by `FitConfig.crop_pad` metres, and kept in an LRU cache bounded by
`FitConfig.cache_mb`; so a THuman4-sized project (24 cameras x 5,000 frames) trains without holding its images in
memory (only the per-frame `PoseTable` is resident).

Ray sampling per step (`RaySampler.sample`): `images_per_batch` images, each a (training frame, training view)
pair drawn uniformly with replacement (from all pairs, or from the sampler's own `pairs`: a ray shard of a
data-parallel fit, fit/distributed.py); the step's `rays_per_batch` rays are split evenly over them. Of an image's
rays, `box_fraction` (default 90%) are drawn uniformly among the pixels inside the projected grown box (the crop's
polygon), the rest uniformly over the whole image.
Rays go through pixel centres (OpenCV convention).

Target colour (stated convention): the masked image over the fixed background colour,
rgb * mask + background * (1 - mask). Pixels outside the crop are taken as background: the crop is the body's box
grown by `crop_pad` (0.25 m by default), beyond the reach of the node fields around the body; a mask pixel there is
ignored.

All randomness comes from the `torch.Generator` passed to `sample`, so a run is reproducible and resumable.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
import torch

from avatarctl.evaluate.protocols import bbox_region, ground_truth
from avatarctl.fit.conditioning import PoseTable, make_conditioning, time_stamps
from avatarctl.io.project_io import ProjectCapture
from avatarctl.model.avatar import FrameConditioning
from avatarctl.geometry.cameras import Camera
from avatarctl.geometry.rays import RayBatch, camera_rays


@dataclass(frozen=True)
class FrameCrop:
    """One (camera, frame) image cropped to its grown body box."""

    x0: int  # crop origin in the full image, pixels
    y0: int
    rgb: np.ndarray  # [h, w, 3] uint8
    mask: np.ndarray  # [h, w] bool foreground
    inside: np.ndarray  # [n] int64 flat indices (into the crop) of the pixels inside the projected box polygon

    @property
    def nbytes(self) -> int:
        return int(self.rgb.nbytes + self.mask.nbytes + self.inside.nbytes)


class FrameStore:
    """Lazy, LRU-cached access to cropped training frames under a RAM budget (bytes)."""

    def __init__(self, capture: ProjectCapture, poses: PoseTable, crop_pad: float, budget_bytes: int):
        self.capture = capture
        self.poses = poses
        self.crop_pad = float(crop_pad)
        self.budget = int(budget_bytes)
        self._cache: OrderedDict[tuple[str, int], FrameCrop] = OrderedDict()
        self._bytes = 0
        self.hits = 0
        self.misses = 0

    @property
    def cached_bytes(self) -> int:
        return self._bytes

    def __len__(self) -> int:
        return len(self._cache)

    def get(self, cam: str, frame: int) -> FrameCrop:
        key = (cam, int(frame))
        crop = self._cache.get(key)
        if crop is not None:
            self.hits += 1
            self._cache.move_to_end(key)
            return crop
        self.misses += 1
        crop = self._load(cam, int(frame))
        self._cache[key] = crop
        self._bytes += crop.nbytes
        while self._bytes > self.budget and len(self._cache) > 1:
            _, old = self._cache.popitem(last=False)
            self._bytes -= old.nbytes
        return crop

    def _load(self, cam: str, frame: int) -> FrameCrop:
        camera = self.capture.cameras[cam]
        row = self.poses.rows([frame])[0]
        corners = np.stack([self.poses.box_lo[row], self.poses.box_hi[row]])  # [2, 3]
        region = bbox_region(camera, corners, pad=self.crop_pad)
        x0, y0, x1, y1 = region.crop
        img = self.capture.image(cam, frame)
        mask = self.capture.mask(cam, frame)
        if img.shape[:2] != (camera.height, camera.width) or mask.shape != img.shape[:2]:
            from avatarctl.errors import ProjectError

            raise ProjectError(f"camera {cam} frame {frame}: image {img.shape[:2]} / mask {mask.shape} do not match "
                               f"the camera's {camera.height}x{camera.width}", where=str(self.capture.project.root),
                               fix="re-run `avatarctl ingest`")
        inside = np.flatnonzero(region.mask[y0:y1, x0:x1])
        return FrameCrop(x0=x0, y0=y0, rgb=np.ascontiguousarray(img[y0:y1, x0:x1]),
                         mask=np.ascontiguousarray(mask[y0:y1, x0:x1]), inside=inside.astype(np.int64))


@dataclass
class TrainBatch:
    """One optimisation step's rays, targets and frame conditioning."""

    rays: RayBatch  # [rays]; frame_slot indexes `cond`
    target: torch.Tensor  # [rays, 3] float32 in [0, 1]: rgb * mask + background * (1 - mask)
    cond: FrameConditioning  # [B]
    frames: list[int]  # [B] capture frame numbers
    views: list[str]  # [B] camera names


def target_colours(crop: FrameCrop, px: np.ndarray, py: np.ndarray, background: np.ndarray) -> np.ndarray:
    """[n, 3] float32 targets at full-image pixels (px, py); outside the crop: background (see module docstring)."""
    h, w = crop.mask.shape
    cx, cy = px - crop.x0, py - crop.y0
    ok = (cx >= 0) & (cx < w) & (cy >= 0) & (cy < h)
    out = np.broadcast_to(background.astype(np.float32), (px.shape[0], 3)).copy()
    out[ok] = ground_truth(crop.rgb[cy[ok], cx[ok]], crop.mask[cy[ok], cx[ok]], background)
    return out


class PairSampler:
    """What both samplers share: the step's (training frame, training view) pairs and their conditioning."""

    def __init__(self, store: FrameStore, train_frames: list[int], train_views: list[str], images_per_batch: int,
                 background: tuple[float, float, float], pairs: list[tuple[int, str]] | None = None):
        self.store = store
        self.pairs = None if pairs is None else [(int(f), str(v)) for f, v in pairs]  # None = every pair
        self.train_frames = sorted(int(f) for f in train_frames)
        self.train_views = list(train_views)
        self.images_per_batch = int(images_per_batch)
        self.background = np.asarray(background, dtype=np.float32)
        cams = store.capture.cameras
        for v in self.train_views:
            if not cams[v].is_pinhole:
                raise ValueError(f"camera {v} has lens distortion; training expects undistorted (ingested) cameras")

    def draw_images(self, generator: torch.Generator) -> tuple[list[int], list[str]]:
        """The step's `images_per_batch` (frame, view) pairs, uniformly with replacement (see the module docstring)."""
        B = self.images_per_batch
        if self.pairs is None:
            fi = torch.randint(len(self.train_frames), (B,), generator=generator).tolist()
            vi = torch.randint(len(self.train_views), (B,), generator=generator).tolist()
            return [self.train_frames[i] for i in fi], [self.train_views[i] for i in vi]
        picks = [self.pairs[i] for i in torch.randint(len(self.pairs), (B,), generator=generator).tolist()]
        return [f for f, _ in picks], [v for _, v in picks]

    def conditioning(self, frames: list[int], device: str | torch.device) -> FrameConditioning:
        rows = self.store.poses.rows(frames)
        time, ids = time_stamps(frames, self.train_frames, are_training=True)
        return make_conditioning(self.store.poses.joint_transforms[rows], self.store.poses.pose_features[rows],
                                 time, ids, device)


class RaySampler(PairSampler):
    """Draws `TrainBatch`es of scattered rays (see the module docstring for the sampling rule)."""

    def __init__(self, store: FrameStore, train_frames: list[int], train_views: list[str], rays_per_batch: int,
                 images_per_batch: int, box_fraction: float, background: tuple[float, float, float],
                 pairs: list[tuple[int, str]] | None = None):
        super().__init__(store, train_frames, train_views, images_per_batch, background, pairs)
        self.rays_per_batch = int(rays_per_batch)
        self.box_fraction = float(box_fraction)

    def sample(self, generator: torch.Generator, device: str | torch.device = "cpu") -> TrainBatch:
        B, R = self.images_per_batch, self.rays_per_batch
        frames, views = self.draw_images(generator)
        counts = [R // B + (1 if b < R % B else 0) for b in range(B)]
        origins, dirs, slots, targets = [], [], [], []
        for b, (frame, view, n) in enumerate(zip(frames, views, counts)):
            cam: Camera = self.store.capture.cameras[view]
            crop = self.store.get(view, frame)
            n_in = int(round(self.box_fraction * n)) if crop.inside.size else 0
            flat = np.zeros(0, np.int64)
            if n_in:
                flat = crop.inside[torch.randint(crop.inside.size, (n_in,), generator=generator).numpy()]
            w = crop.mask.shape[1]
            u = torch.randint(cam.width * cam.height, (n - n_in,), generator=generator).numpy()
            px = np.concatenate([crop.x0 + flat % w, u % cam.width])
            py = np.concatenate([crop.y0 + flat // w, u // cam.width])
            targets.append(target_colours(crop, px, py, self.background))
            o, d = camera_rays(cam, torch.from_numpy(np.stack([px, py], axis=1).astype(np.float32)))
            origins.append(o)
            dirs.append(d)
            slots.append(torch.full((n,), b, dtype=torch.long))
        cond = self.conditioning(frames, device)
        rays = RayBatch(origins=torch.cat(origins).to(device, torch.float32),
                        dirs=torch.cat(dirs).to(device, torch.float32), frame_slot=torch.cat(slots).to(device))
        return TrainBatch(rays=rays, target=torch.from_numpy(np.concatenate(targets)).to(device), cond=cond,
                          frames=frames, views=views)


@dataclass
class CropTarget:
    """One training image of an `ImageBatch`: the crop window of a camera and its target."""

    camera: Camera  # the full (undistorted) camera
    x0: int  # crop window in the full image, pixels
    y0: int
    target: torch.Tensor  # [h, w, 3] float32: rgb * mask + background * (1 - mask)
    mask: torch.Tensor  # [h, w] float32 foreground


@dataclass
class ImageBatch:
    """One optimisation step of the rasterized field (`model.field = "gaussians"`): whole image crops."""

    crops: list[CropTarget]  # [B]; crop b is frame slot b of `cond`
    cond: FrameConditioning  # [B]
    frames: list[int]
    views: list[str]

    @property
    def pixels(self) -> int:
        return sum(int(c.mask.numel()) for c in self.crops)


class ImageSampler(PairSampler):
    """Draws `ImageBatch`es: the same (frame, view) pairs as `RaySampler` (`draw_images`), each image's whole crop
    (the posed body's box grown by `crop_pad`, see the module docstring) as its target instead of scattered rays."""

    def sample(self, generator: torch.Generator, device: str | torch.device = "cpu") -> ImageBatch:
        frames, views = self.draw_images(generator)
        crops = []
        for frame, view in zip(frames, views):
            crop = self.store.get(view, frame)
            target = ground_truth(crop.rgb, crop.mask, self.background).astype(np.float32)
            crops.append(CropTarget(camera=self.store.capture.cameras[view], x0=crop.x0, y0=crop.y0,
                                    target=torch.from_numpy(target).to(device),
                                    mask=torch.from_numpy(crop.mask.astype(np.float32)).to(device)))
        return ImageBatch(crops=crops, cond=self.conditioning(frames, device), frames=frames, views=views)
