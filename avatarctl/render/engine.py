"""Render one whole view of a fitted avatar: `render_view`, which asks the model's kind of local field
(`model.field_kind`, model/local_field.py) to render it with one of the two renderers here:

`rasterize_view` (the Gaussian local fields): the whole image rasterized at once (avatarctl/splat).

`march_view` (the ray-marched fields):
1. candidate pixels: every pixel (or those of `pixel_mask`) whose camera ray passes within the node-support radius
   sigma * sqrt(-2 ln eps) of at least one posed node of the frame (Eq. 6: the blending weight is exactly zero
   farther away, so no other ray can see the avatar). The test is exact for the spheres (ray-to-centre distance),
   not a screen-space approximation, and runs in chunks;
2. those rays are rendered by `model.render` in chunks of at most `max_rays_per_chunk` rays under `torch.no_grad()`
   (the chunk bounds peak memory: roughly chunk x samples_per_ray x touched nodes);
3. every other pixel is `background` with alpha 0.

Conventions: pinhole camera (OpenCV, world->camera, metres; undistorted images); pixel centres at integer
coordinates; output row-major [H, W].
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
import torch

from avatarctl.geometry.cameras import Camera
from avatarctl.progress import ProgressFn, ProgressReport

if TYPE_CHECKING:
    from avatarctl.geometry.rays import RayBatch
    from avatarctl.splat import SplatCamera


class NodeFrames(Protocol):
    """The posed nodes of a batch of frames, as the engine reads them (`model.avatar.NodeState` is one)."""

    @property
    def centers(self) -> torch.Tensor: ...  # [frames, nodes, 3] posed node positions n_i, world, metres

    def frame(self, slot: int) -> "NodeFrames": ...  # the nodes of frame `slot` alone (a batch of one)


class SupportConfig(Protocol):
    """The setting of a model's config the engine reads (`model.config.ModelConfig` is one)."""

    @property
    def support_radius(self) -> float: ...  # Eq. 6 support radius of a node, metres


class ViewField(Protocol):
    """How a model's kind of local field renders a whole view (`model.local_field.LocalField` is one): it calls
    `march_view` or `rasterize_view` below."""

    def render_view(self, model: Any, state: Any, slot: int, camera: Camera, background: tuple[float, float, float],
                    max_rays_per_chunk: int, pixel_mask: np.ndarray | None, progress: ProgressFn | None
                    ) -> "ViewRender": ...


class ViewModel(Protocol):
    """What `render_view` needs of a model (`model.avatar.SlrfAvatar` is one): its kind of local field, and rays
    rendered against the nodes of a frame (ray-marched fields) or the posed Gaussians rasterized (Gaussian fields).
    The engine knows no more of the model than this, so `render/` sits below `model/` (which composites with
    `render.volume`)."""

    @property
    def cfg(self) -> SupportConfig: ...

    @property
    def field_kind(self) -> ViewField: ...

    def render(self, rays: "RayBatch", state: Any, background: torch.Tensor, *, jitter: bool = False) -> Any: ...
    # -> outputs with .rgb [rays, 3] and .alpha [rays]

    def posed_gaussians(self, state: Any) -> Any: ...

    def render_image(self, posed: Any, slot: int, camera: "SplatCamera", background: torch.Tensor
                     ) -> tuple[torch.Tensor, torch.Tensor]: ...  # rgb [H, W, 3], alpha [H, W]


@dataclass
class ViewRender:
    """One rendered view."""

    rgb: np.ndarray  # [H, W, 3] float32 in [0, 1], composited over `background`
    alpha: np.ndarray  # [H, W] float32 accumulated opacity
    seconds: float  # wall time of the call
    rays: int = 0  # rays actually rendered (pixels that can hit the node-influence region)


def support_radius(model: ViewModel) -> float:
    """Eq. 6 support radius of a node, metres."""
    return float(model.cfg.support_radius)


def rays_hitting_spheres(origin: torch.Tensor, dirs: torch.Tensor, centers: torch.Tensor, radius: float,
                         chunk: int = 65536) -> torch.Tensor:
    """[rays] bool: does the ray `origin + t * dirs` (t > 0) pass within `radius` of any of `centers`?

    origin [3] (one camera centre), dirs [rays, 3] unit, centers [nodes, 3]; world metres.
    """
    v = centers - origin  # [nodes, 3]
    vv = (v * v).sum(-1)  # [nodes]
    r2 = radius * radius
    inside = vv <= r2  # camera inside a sphere: every ray hits it
    out = torch.empty(dirs.shape[0], dtype=torch.bool, device=dirs.device)
    for s in range(0, dirs.shape[0], chunk):
        t = dirs[s:s + chunk] @ v.T  # [rays, nodes] distance along the ray to the closest point
        d2 = vv[None] - t * t  # squared ray-to-centre distance
        hit = ((d2 <= r2) & (t > 0)) | inside[None]
        out[s:s + chunk] = hit.any(dim=1)
    return out


def render_view(model: ViewModel, state: NodeFrames, slot: int, camera: Camera,
                background: tuple[float, float, float], max_rays_per_chunk: int = 8192,
                pixel_mask: np.ndarray | None = None, progress: ProgressFn | None = None) -> ViewRender:
    """Render frame `slot` of `state` (a `NodeState` batched over frames) seen by `camera`.

    `pixel_mask` [H, W] bool restricts rendering to those pixels (e.g. the eval box); pixels outside it are
    `background` with alpha 0. `progress` gets a report after each chunk (`part` "rays": rays rendered of the rays
    to render).
    """
    if not camera.is_pinhole:
        raise ValueError(f"render_view needs a pinhole camera (camera {camera.name} has distortion); "
                         "use camera.pinhole() for undistorted images")
    if not 0 <= slot < state.centers.shape[0]:
        raise IndexError(f"slot {slot} outside the NodeState batch of {state.centers.shape[0]} frames")
    if pixel_mask is not None and np.asarray(pixel_mask).shape != (int(camera.height), int(camera.width)):
        raise ValueError(f"pixel_mask {np.asarray(pixel_mask).shape} does not match the camera's image "
                         f"({int(camera.height)}, {int(camera.width)})")
    return model.field_kind.render_view(model, state, slot, camera, background, max_rays_per_chunk, pixel_mask,
                                        progress)


def march_view(model: ViewModel, state: NodeFrames, slot: int, camera: Camera,
               background: tuple[float, float, float], max_rays_per_chunk: int = 8192,
               pixel_mask: np.ndarray | None = None, progress: ProgressFn | None = None) -> ViewRender:
    """`render_view` for the ray-marched fields: steps 1-3 of the module docstring."""
    from avatarctl.geometry.rays import RayBatch, camera_rays, image_pixels

    t0 = time.perf_counter()
    H, W = int(camera.height), int(camera.width)
    device = state.centers.device
    bg = torch.tensor(background, dtype=torch.float32, device=device)
    rgb = np.empty((H * W, 3), dtype=np.float32)
    rgb[:] = np.asarray(background, dtype=np.float32)
    alpha = np.zeros(H * W, dtype=np.float32)

    pixels = image_pixels(W, H).to(device)  # [H*W, 2] (x, y)
    candidates = torch.arange(H * W, device=device)
    if pixel_mask is not None:
        m = np.asarray(pixel_mask, dtype=bool)
        candidates = torch.from_numpy(np.flatnonzero(m)).to(device)
    with torch.no_grad():
        if candidates.numel():
            origins, dirs = camera_rays(camera, pixels[candidates])
            hit = rays_hitting_spheres(origins[0], dirs, state.centers[slot].float(), support_radius(model))
            candidates, origins, dirs = candidates[hit], origins[hit], dirs[hit]
        total = int(candidates.numel())
        for s in range(0, total, max_rays_per_chunk):
            e = min(s + max_rays_per_chunk, total)
            rays = RayBatch(origins=origins[s:e], dirs=dirs[s:e],
                            frame_slot=torch.full((e - s,), slot, dtype=torch.long, device=device))
            out = model.render(rays, state, bg, jitter=False)
            idx = candidates[s:e].cpu().numpy()
            rgb[idx] = out.rgb.float().cpu().numpy()
            alpha[idx] = out.alpha.float().cpu().numpy()
            if progress is not None:
                progress(ProgressReport(done=e, total=total, part="rays"))
    return ViewRender(rgb=np.clip(rgb, 0.0, 1.0).reshape(H, W, 3), alpha=alpha.reshape(H, W),
                      seconds=time.perf_counter() - t0, rays=total)


def rasterize_view(model: ViewModel, state: NodeFrames, slot: int, camera: Camera,
                   background: tuple[float, float, float], pixel_mask: np.ndarray | None = None,
                   progress: ProgressFn | None = None) -> ViewRender:
    """`render_view` for the Gaussian local fields: the whole image rasterized at once (avatarctl/splat); pixels
    outside `pixel_mask` set to the background with alpha 0 afterwards. `rays` counts the pixels rendered."""
    from avatarctl.splat import SplatCamera

    t0 = time.perf_counter()
    H, W = int(camera.height), int(camera.width)
    state = state.frame(slot)
    device = state.centers.device
    with torch.no_grad():
        posed = model.posed_gaussians(state)
        rgb_t, alpha_t = model.render_image(posed, 0, SplatCamera.from_camera(camera, device=device),
                                            torch.tensor(background, dtype=torch.float32, device=device))
        rgb = rgb_t.float().clamp_(0.0, 1.0).cpu().numpy()  # clamped where the image is (a GPU's, not the host's)
        alpha = alpha_t.float().cpu().numpy()
    if pixel_mask is not None:
        keep = np.asarray(pixel_mask, dtype=bool)
        rgb[~keep] = np.asarray(background, dtype=np.float32)
        alpha[~keep] = 0.0
    if progress is not None:
        progress(ProgressReport(done=H * W, total=H * W, part="rays"))
    return ViewRender(rgb=rgb, alpha=alpha, seconds=time.perf_counter() - t0, rays=H * W)
