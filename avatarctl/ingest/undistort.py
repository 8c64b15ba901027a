"""Undistortion and resizing of frames and masks (OpenCV), and the matching pinhole camera.

The project keeps the capture's K: ``cv2.undistort`` with ``newK = K`` (no cropping, no zoom), so the stored
camera is the calibrated one with ``dist = 0``. Images are resampled bilinearly, masks with nearest neighbour.
Resizing (``--resize s``) follows undistortion and uses `Camera.scaled` (cv2.resize pixel-centre convention).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from avatarctl.geometry.cameras import Camera


@dataclass(frozen=True)
class Undistorter:
    """Per-camera remap tables (built once) taking distorted capture pixels to the output pinhole camera."""

    source: Camera  # as calibrated, with distortion
    target: Camera  # pinhole, possibly scaled
    map_x: np.ndarray | None  # [H, W] float32, None when the source is already pinhole
    map_y: np.ndarray | None  # [H, W] float32

    @classmethod
    def for_camera(cls, cam: Camera, scale: float = 1.0) -> "Undistorter":
        import cv2

        target = cam.pinhole() if scale == 1.0 else cam.pinhole().scaled(scale)
        if cam.is_pinhole:
            return cls(cam, target, None, None)
        mx, my = cv2.initUndistortRectifyMap(cam.K, cam.dist, None, cam.K, (cam.width, cam.height), cv2.CV_32FC1)
        return cls(cam, target, mx, my)

    def _resize(self, img: np.ndarray, interp: int) -> np.ndarray:
        import cv2

        if (img.shape[1], img.shape[0]) == (self.target.width, self.target.height):
            return img
        return cv2.resize(img, (self.target.width, self.target.height), interpolation=interp)

    def image(self, rgb: np.ndarray) -> np.ndarray:
        """[H, W, 3] uint8 distorted -> [h, w, 3] uint8 undistorted (and resized)."""
        import cv2

        if self.map_x is not None:
            rgb = cv2.remap(rgb, self.map_x, self.map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        shrink = self.target.width < self.source.width
        return self._resize(rgb, cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)

    def mask(self, mask: np.ndarray) -> np.ndarray:
        """[H, W] bool distorted -> [h, w] bool undistorted (nearest), resized by area coverage >= 50 %."""
        import cv2

        m = mask.astype(np.uint8) * 255
        if self.map_x is not None:
            m = cv2.remap(m, self.map_x, self.map_y, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT)
        shrink = self.target.width < self.source.width
        m = self._resize(m, cv2.INTER_AREA if shrink else cv2.INTER_NEAREST)
        return m >= 128
