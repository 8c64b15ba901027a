"""The camera the rasterizer projects with: a pinhole as torch tensors.

Conventions (those of `avatarctl.geometry.cameras.Camera`): metres; world->camera `x_cam = R @ x_world + T`; the
camera looks down +z, image x right, y down; pixel centres at integer coordinates (pixel (x, y) is at u = x, v = y).
No lens distortion: splatting projects the Gaussian centres through `K` only (undistort the images first).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch


@dataclass(frozen=True)
class SplatCamera:
    """One pinhole camera seeing a `width` x `height` window."""

    K: torch.Tensor  # [3, 3] intrinsics, pixels (skew K[0, 1] allowed)
    R: torch.Tensor  # [3, 3] world->camera rotation
    T: torch.Tensor  # [3] world->camera translation, metres
    width: int
    height: int

    def __post_init__(self) -> None:
        for name, shape in (("K", (3, 3)), ("R", (3, 3)), ("T", (3,))):
            value = getattr(self, name)
            assert tuple(value.shape) == shape, f"SplatCamera.{name}: expected {list(shape)}, got {list(value.shape)}"
        if not (self.width > 0 and self.height > 0):
            raise ValueError(f"SplatCamera: image size must be positive, got {self.width}x{self.height}")

    @property
    def center(self) -> torch.Tensor:
        """Camera centre in world coordinates, [3] (as `geometry.Camera.center`)."""
        return -(self.R.T @ self.T)

    @staticmethod
    def from_camera(cam, device: torch.device | str | None = None) -> "SplatCamera":
        """From a calibrated `Camera` (numpy, float64) -> float32 tensors on `device`. A camera with lens distortion
        is refused: splat into undistorted images with `cam.pinhole()`."""
        if not cam.is_pinhole:
            raise ValueError(f"camera {cam.name}: has lens distortion {list(cam.dist)}; splatting needs a pinhole "
                             "camera (undistort the images and pass cam.pinhole())")

        # one host-to-device copy for the three (each copy costs a GPU render more than its bytes)
        packed = torch.from_numpy(np.concatenate([np.ravel(cam.K), np.ravel(cam.R), np.ravel(cam.T)]).astype(
            np.float32)).to(device)
        return SplatCamera(K=packed[:9].view(3, 3), R=packed[9:18].view(3, 3), T=packed[18:21], width=int(cam.width),
                           height=int(cam.height))

    def crop(self, x0: int, y0: int, width: int, height: int) -> "SplatCamera":
        """The camera of the sub-window whose top-left pixel is (x0, y0) of this image: the principal point moves by
        (-x0, -y0). The window may reach outside the image (it is a camera, not a slice)."""
        K = self.K.clone()
        K[0, 2] -= x0
        K[1, 2] -= y0
        return replace(self, K=K, width=int(width), height=int(height))

    def to(self, device: torch.device | str) -> "SplatCamera":
        """The same camera with its tensors on `device`."""
        return replace(self, K=self.K.to(device), R=self.R.to(device), T=self.T.to(device))
