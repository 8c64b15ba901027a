"""Ray casting through real lenses: one ray per (sub)pixel of the *distorted* image, cast with Warp.

Each pixel centre (u, v) of the saved (distorted) image is mapped to normalised distorted coordinates
x_d = K^-1 (u, v, 1), undistorted by inverting OpenCV's radial-tangential model (fixed-point iteration, the same
scheme as `cv2.undistortPoints`), and becomes the world ray o = C, d = R^T (x_u, y_u, 1) / |.|. Rendering along
these rays yields the distorted image directly, so `cv2.undistort(image, K, dist)` equals a pinhole render up to
resampling. Supersampling casts `ss x ss` rays per pixel at offsets (k + 0.5) / ss - 0.5.
Conventions: OpenCV cameras (world->camera, metres, pixel centres at integers), see `avatarctl.geometry.cameras`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from avatarctl.geometry.cameras import Camera, distort_normalized


def undistort_normalized(xy_d: np.ndarray, dist: np.ndarray, iters: int = 40) -> np.ndarray:
    """Invert `distort_normalized`: distorted normalised coords [..., 2] -> undistorted [..., 2]."""
    k1, k2, p1, p2, k3 = np.asarray(dist, dtype=np.float64).ravel()[:5]
    xy_d = np.asarray(xy_d, dtype=np.float64)
    x, y = xy_d[..., 0].copy(), xy_d[..., 1].copy()
    for _ in range(iters):
        r2 = x * x + y * y
        radial = 1 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2
        dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        x = (xy_d[..., 0] - dx) / radial
        y = (xy_d[..., 1] - dy) / radial
    return np.stack([x, y], -1)


@dataclass(frozen=True)
class RayGrid:
    """World rays of every subpixel of one camera's distorted image."""

    origin: np.ndarray  # [3] camera centre, world, metres
    dirs: np.ndarray  # [H * ss, W * ss, 3] float32 unit directions, world
    ss: int  # subpixels per pixel along each axis


def camera_rays(cam: Camera, ss: int = 1) -> RayGrid:
    """The ray grid of `cam` (with its distortion; pass `cam.pinhole()` for an undistorted render)."""
    offs = (np.arange(ss) + 0.5) / ss - 0.5
    u = (np.arange(cam.width)[:, None] + offs[None]).ravel()  # [W * ss]
    v = (np.arange(cam.height)[:, None] + offs[None]).ravel()  # [H * ss]
    uu, vv = np.meshgrid(u, v)  # [H*ss, W*ss]
    K = cam.K
    xd = (uu - K[0, 2] - K[0, 1] * (vv - K[1, 2]) / K[1, 1]) / K[0, 0]
    yd = (vv - K[1, 2]) / K[1, 1]
    xy = np.stack([xd, yd], -1)
    if not cam.is_pinhole:
        xy = undistort_normalized(xy, cam.dist)
        resid = np.abs(distort_normalized(xy, cam.dist) - np.stack([xd, yd], -1)).max()
        if resid > 1e-6:
            raise ValueError(f"camera {cam.name}: lens distortion is not invertible over the image "
                             f"(residual {resid:.2e}); use smaller k1/k2")
    d_cam = np.concatenate([xy, np.ones_like(xy[..., :1])], -1)
    d = d_cam @ cam.R  # rows: R^T d_cam
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return RayGrid(origin=cam.center, dirs=d.astype(np.float32), ss=ss)
