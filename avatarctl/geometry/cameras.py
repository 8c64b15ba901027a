"""Calibrated cameras (OpenCV convention) as a typed container, and projection helpers.

Conventions: metres; world->camera `x_cam = R @ x_world + T`; camera looks down +z, image x right, y down;
pixel centres at integer coordinates (OpenCV); distortion `dist = (k1, k2, p1, p2, k3)` (OpenCV order).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

ROTATION_TOL = 1e-3  # max |R R^T - I|: calibration files store R to 6+ digits; a scaled or sheared R is far off


def scaled_intrinsics(K, factor: float):
    """[3, 3] intrinsics (numpy or torch) of images resized by `factor` -> a new K: focal lengths and skew times
    `factor`, the principal point by cv2.resize's pixel-centre convention (pixel centres at integers: u' = (u + 0.5)
    factor - 0.5)."""
    K = K.clone() if hasattr(K, "clone") else K.copy()
    K[:2, :2] *= factor
    K[:2, 2] = (K[:2, 2] + 0.5) * factor - 0.5
    return K


@dataclass(frozen=True)
class Camera:
    """One calibrated camera."""

    name: str
    K: np.ndarray  # [3, 3] intrinsics (pixels)
    R: np.ndarray  # [3, 3] world->camera rotation
    T: np.ndarray  # [3] world->camera translation (metres)
    width: int
    height: int
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))  # [5] k1 k2 p1 p2 k3

    def __post_init__(self) -> None:
        object.__setattr__(self, "K", np.asarray(self.K, dtype=np.float64).reshape(3, 3))
        object.__setattr__(self, "R", np.asarray(self.R, dtype=np.float64).reshape(3, 3))
        object.__setattr__(self, "T", np.asarray(self.T, dtype=np.float64).reshape(3))
        d = np.zeros(5)
        dd = np.asarray(self.dist, dtype=np.float64).ravel()
        if dd.size not in (0, 4, 5) and (dd.size < 5 or np.any(dd[5:])):
            raise ValueError(f"camera {self.name}: distortion has {dd.size} coefficients; expected 4 or 5 "
                             "(k1 k2 p1 p2 [k3], OpenCV order)")
        d[: min(5, dd.size)] = dd[:5]
        object.__setattr__(self, "dist", d)
        if not (np.isfinite(self.K).all() and np.isfinite(self.R).all() and np.isfinite(self.T).all()
                and np.isfinite(d).all()):
            raise ValueError(f"camera {self.name}: non-finite calibration (NaN or inf in K, R, T or dist)")
        err = np.abs(self.R @ self.R.T - np.eye(3)).max()
        if err > ROTATION_TOL or np.linalg.det(self.R) < 0:
            raise ValueError(f"camera {self.name}: R is not a rotation (|R R^T - I| = {err:.3g}, det "
                             f"{np.linalg.det(self.R):.3g}; expected orthonormal with det +1)")
        if not (self.K[0, 0] > 0 and self.K[1, 1] > 0 and self.width > 0 and self.height > 0):
            raise ValueError(f"camera {self.name}: focal lengths and image size must be positive (fx "
                             f"{self.K[0, 0]:g}, fy {self.K[1, 1]:g}, {self.width}x{self.height})")

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates, [3]."""
        return -self.R.T @ self.T

    @property
    def is_pinhole(self) -> bool:
        return not np.any(self.dist)

    def pinhole(self) -> "Camera":
        """The same camera with zero distortion (what undistorted images are taken with)."""
        return replace(self, dist=np.zeros(5))

    def scaled(self, factor: float) -> "Camera":
        """The camera for images resized by `factor` (pixel-centre convention of cv2.resize)."""
        return replace(self, K=scaled_intrinsics(self.K, factor), width=int(round(self.width * factor)),
                       height=int(round(self.height * factor)))

    def world_to_camera(self, X: np.ndarray) -> np.ndarray:
        """[..., 3] world points -> [..., 3] camera coordinates."""
        return X @ self.R.T + self.T

    def project(self, X: np.ndarray, distort: bool = True) -> np.ndarray:
        """[..., 3] world points -> [..., 2] pixel coordinates (OpenCV model incl. distortion unless disabled)."""
        Xc = self.world_to_camera(np.asarray(X, dtype=np.float64))
        z = Xc[..., 2:3]
        xy = Xc[..., :2] / np.where(np.abs(z) < 1e-12, 1e-12, z)
        if distort and not self.is_pinhole:
            xy = distort_normalized(xy, self.dist)
        return xy @ self.K[:2, :2].T + self.K[:2, 2]

    def to_json(self) -> dict[str, Any]:
        return {"name": self.name, "K": self.K.tolist(), "R": self.R.tolist(), "T": self.T.tolist(),
                "width": self.width, "height": self.height, "dist": self.dist.tolist()}

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> "Camera":
        return cls(name=str(d["name"]), K=np.array(d["K"]), R=np.array(d["R"]), T=np.array(d["T"]),
                   width=int(d["width"]), height=int(d["height"]), dist=np.array(d.get("dist", np.zeros(5))))


def distort_normalized(xy: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Apply OpenCV's radial-tangential distortion to normalised image coordinates, [..., 2] -> [..., 2]."""
    k1, k2, p1, p2, k3 = np.asarray(dist, dtype=np.float64).ravel()[:5]
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([xd, yd], axis=-1)


def look_at(eye: np.ndarray, target: np.ndarray,
            up: np.ndarray = np.array([0.0, 0.0, 1.0])) -> tuple[np.ndarray, np.ndarray]:
    """World->camera (R, T) for a camera at `eye` looking at `target` (OpenCV axes: x right, y down, z forward)."""
    eye = np.asarray(eye, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-8:  # looking straight along `up`
        x = np.cross(z, np.array([0.0, 1.0, 0.0]))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z], axis=0)
    return R, -R @ eye
