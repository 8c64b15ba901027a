"""Camera rays: pixel centres -> world-space rays (OpenCV pinhole camera, metres).

Convention (see `cameras.py`): x_cam = R x_world + T; the camera looks down +z, x right, y down; pixel centres at
integer coordinates. Images are undistorted at ingest, so rays are cast with the pinhole model only.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from avatarctl.geometry.cameras import Camera


@dataclass
class RayBatch:
    """A batch of rays, each belonging to one of the B frames of a `NodeState`."""

    origins: torch.Tensor  # [rays, 3] world, metres
    dirs: torch.Tensor  # [rays, 3] unit length, world
    frame_slot: torch.Tensor  # [rays] long, index into the batch of frames B of the NodeState

    def __post_init__(self) -> None:
        R = self.origins.shape[0]
        assert self.origins.shape == (R, 3), f"origins: expected [rays, 3], got {tuple(self.origins.shape)}"
        assert self.dirs.shape == (R, 3), f"dirs: expected [{R}, 3], got {tuple(self.dirs.shape)}"
        assert self.frame_slot.shape == (R,), f"frame_slot: expected [{R}], got {tuple(self.frame_slot.shape)}"
        assert not self.frame_slot.is_floating_point(), f"frame_slot must be integer, got {self.frame_slot.dtype}"

    def __len__(self) -> int:
        return self.origins.shape[0]

    def to(self, device: torch.device | str) -> "RayBatch":
        return RayBatch(self.origins.to(device), self.dirs.to(device), self.frame_slot.to(device))

    def select(self, idx: torch.Tensor | slice) -> "RayBatch":
        """The rays at `idx` (index tensor, boolean mask or slice)."""
        return RayBatch(self.origins[idx], self.dirs[idx], self.frame_slot[idx])

    @staticmethod
    def cat(batches: list["RayBatch"]) -> "RayBatch":
        return RayBatch(torch.cat([b.origins for b in batches]), torch.cat([b.dirs for b in batches]),
                        torch.cat([b.frame_slot for b in batches]))


def image_pixels(width: int, height: int) -> torch.Tensor:
    """[H*W, 2] float32 pixel centres (x, y) in row-major order (x fastest): index = y * width + x."""
    ys, xs = torch.meshgrid(torch.arange(height, dtype=torch.float32), torch.arange(width, dtype=torch.float32),
                            indexing="ij")
    return torch.stack([xs.reshape(-1), ys.reshape(-1)], dim=-1)


def camera_rays(cam: Camera, pixels: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Rays through pixel centres of a pinhole camera.

    pixels [rays, 2] (x, y) in OpenCV pixel coordinates -> origins [rays, 3] (the camera centre, world, metres),
    dirs [rays, 3] (unit, world). Same dtype/device as `pixels` (float32 if integer).
    """
    if not cam.is_pinhole:
        raise ValueError(f"camera {cam.name}: camera_rays needs a pinhole camera; undistort the images and use "
                         "cam.pinhole()")
    assert pixels.ndim == 2 and pixels.shape[1] == 2, f"pixels: expected [rays, 2], got {tuple(pixels.shape)}"
    dtype = pixels.dtype if pixels.is_floating_point() else torch.float32
    px = pixels.to(dtype)
    K = torch.as_tensor(cam.K, dtype=torch.float64)
    R = torch.as_tensor(cam.R, dtype=torch.float64)
    T = torch.as_tensor(cam.T, dtype=torch.float64)
    p = px.to(torch.float64).cpu()
    x = (p[:, 0] - K[0, 2] - K[0, 1] * (p[:, 1] - K[1, 2]) / K[1, 1]) / K[0, 0]
    y = (p[:, 1] - K[1, 2]) / K[1, 1]
    d_cam = torch.stack([x, y, torch.ones_like(x)], dim=-1)  # [rays, 3]
    d = d_cam @ R  # = (R^T d_cam^T)^T: camera -> world rotation
    d = d / d.norm(dim=-1, keepdim=True)
    center = -(R.T @ T)
    origins = center.expand_as(d)
    return origins.to(device=pixels.device, dtype=dtype).contiguous(), d.to(device=pixels.device, dtype=dtype)
