"""Camera trajectories for free-viewpoint rendering: an orbit around the subject.

Conventions: metres, world frame of the project, OpenCV cameras (world->camera, x right, y down, z forward).
The world "up" direction is not the same in every capture (anny/AMASS: +z; other rigs differ), so it is estimated
from the capture's cameras (`up_from_cameras`: the mean of their image-up directions -R[1]), which holds for any rig
whose cameras are roughly upright.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from avatarctl.geometry.cameras import Camera, look_at


@dataclass(frozen=True)
class OrbitSpec:
    """An orbit: `views` cameras evenly spaced over one full turn around the subject."""

    views: int  # number of cameras over 360°
    elevation_deg: float = 10.0  # camera height above the subject's centre, as an angle (degrees, + = looking down)
    radius: float | None = None  # metres from the centre; None = mean distance of the capture cameras
    resolution: int = 256  # square images, pixels
    fill: float = 0.9  # fraction of the image the subject's bounding sphere spans
    start_azimuth_deg: float = 0.0  # azimuth of the first view, relative to `reference_dir`

    def __post_init__(self) -> None:
        if self.views < 1:
            raise ValueError(f"orbit needs at least 1 view, got {self.views}")
        if not -89.0 <= self.elevation_deg <= 89.0:
            raise ValueError(f"elevation {self.elevation_deg}° outside [-89, 89]")
        if self.radius is not None and not self.radius > 0:
            raise ValueError(f"orbit radius must be > 0 metres, got {self.radius}")
        if self.resolution < 8:
            raise ValueError(f"resolution {self.resolution} px is too small (min 8)")
        if not 0.05 <= self.fill <= 1.0:
            raise ValueError(f"fill {self.fill} outside [0.05, 1]")


def up_from_cameras(cameras: list[Camera]) -> np.ndarray:
    """[3] unit world-up estimated from upright cameras: the mean of their image-up axes (-y of the camera)."""
    ups = np.stack([-c.R[1] for c in cameras])  # [cams, 3] camera -y axis in world coordinates
    up = ups.mean(axis=0)
    n = np.linalg.norm(up)
    if n < 1e-6:
        return np.array([0.0, 0.0, 1.0])
    return up / n


def smooth_centers(centers: np.ndarray, window: int = 9) -> np.ndarray:
    """[frames, 3] -> [frames, 3] moving average (edge-padded), so a tracking camera does not shake."""
    c = np.asarray(centers, dtype=np.float64)
    if c.shape[0] <= 1 or window <= 1:
        return c.copy()
    w = min(window, c.shape[0] if c.shape[0] % 2 else c.shape[0] - 1)
    w = max(w, 1)
    pad = w // 2
    padded = np.concatenate([np.repeat(c[:1], pad, 0), c, np.repeat(c[-1:], pad, 0)])
    kernel = np.ones(w) / w
    return np.stack([np.convolve(padded[:, i], kernel, mode="valid") for i in range(3)], axis=1)


def orbit_cameras(spec: OrbitSpec, centers: np.ndarray, extent: float, up: np.ndarray, radius: float,
                  reference_dir: np.ndarray | None = None) -> list[Camera]:
    """One camera per orbit step k = 0..views-1 at azimuth start + 360°·k/views around `centers[k]`.

    centers: [views, 3] the point each camera looks at (world, metres), e.g. the subject's smoothed box centre;
    extent: radius (metres) of a sphere around the centre that holds the subject, framed to `spec.fill` of the image;
    up: [3] world up; radius: camera distance (metres); reference_dir: [3] horizontal direction of azimuth 0
    (e.g. towards the first capture camera); defaults to a vector perpendicular to `up`.
    Intrinsics: square pixels, principal point at the image centre.
    """
    centers = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    assert centers.shape[0] == spec.views, f"centers {centers.shape} for {spec.views} views"
    up = np.asarray(up, dtype=np.float64)
    up = up / np.linalg.norm(up)
    if reference_dir is None:
        reference_dir = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.asarray(reference_dir, dtype=np.float64) - up * float(np.dot(reference_dir, up))
    if np.linalg.norm(e1) < 1e-6:
        e1 = np.cross(up, np.array([1.0, 0.0, 0.0]))
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    if radius <= extent:
        raise ValueError(f"orbit radius {radius:.2f} m is inside the subject (extent {extent:.2f} m): "
                         "use a larger radius")
    res = spec.resolution
    half_angle = math.asin(min(extent / radius, 0.999))
    focal = (res / 2.0) * spec.fill / math.tan(half_angle)
    K = np.array([[focal, 0.0, (res - 1) / 2.0], [0.0, focal, (res - 1) / 2.0], [0.0, 0.0, 1.0]])
    el = math.radians(spec.elevation_deg)
    cams = []
    for k in range(spec.views):
        az = math.radians(spec.start_azimuth_deg) + 2.0 * math.pi * k / spec.views
        horiz = math.cos(az) * e1 + math.sin(az) * e2
        eye = centers[k] + radius * (math.cos(el) * horiz + math.sin(el) * up)
        R, T = look_at(eye, centers[k], up=up)
        cams.append(Camera(name=f"orbit{k:03d}", K=K, R=R, T=T, width=res, height=res))
    return cams


def orbit_defaults(cameras: list[Camera], center: np.ndarray, up: np.ndarray) -> tuple[float, float, np.ndarray]:
    """From the capture cameras: (mean distance to `center` in metres, mean elevation in degrees, reference dir [3])."""
    up = np.asarray(up, dtype=np.float64)
    offs = np.stack([c.center for c in cameras]) - np.asarray(center, dtype=np.float64)  # [cams, 3]
    dist = np.linalg.norm(offs, axis=1)
    elev = np.degrees(np.arcsin(np.clip((offs @ up) / np.maximum(dist, 1e-9), -1.0, 1.0)))
    ref = offs[0] - up * float(offs[0] @ up)
    return float(dist.mean()), float(elev.mean()), ref
