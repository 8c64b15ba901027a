"""Evaluation protocols: which pixels a score is computed over.

- `bbox` (Neural Body / SLRF): project the 8 corners of the posed body mesh's 3D bounding box into the image; PSNR
  over the pixels inside the projected box polygon (`mask_at_box`), SSIM on the image cropped to the polygon's 2D
  bounding rectangle.
- `full`: all pixels; the background colour used for rendering and ground-truth compositing is recorded.
- `mpmavatar` (MPMAvatar's eval.py for ActorsHQ): near-white pixels (rgb mean > 0.9) of each image zeroed, then
  both images multiplied by the ground-truth mask eroded 5 times by a 3x3 square and blurred by a 5x5 Gaussian
  (`mpmavatar_images`); PSNR and SSIM over every pixel of the results.
- `mpmavatar_4d_dress` (the same eval.py for 4D-DRESS): the mask product without the near-white cut.

Ground truth (`ground_truth`, the one compositing rule of fit targets, validation and eval): the undistorted frame
composited with its mask over the background colour the avatar is trained / rendered over.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from avatarctl.geometry.cameras import Camera

PROTOCOLS = ("bbox", "full", "mpmavatar", "mpmavatar_4d_dress")
WHITE_CUT = 0.9  # mpmavatar: pixels whose rgb mean exceeds this are zeroed (eval.py's white-background cut)
GROUND_TRUTH = "undistorted ingest frame * mask + background * (1 - mask)"


def ground_truth(rgb: np.ndarray, mask: np.ndarray, background) -> np.ndarray:
    """[..., 3] uint8 (or float in [0, 1]) colours and [...] mask (bool or float) -> [..., 3] float32
    rgb * mask + background * (1 - mask) (`GROUND_TRUTH`)."""
    a = np.asarray(rgb)
    img = a.astype(np.float32) / 255.0 if a.dtype == np.uint8 else a.astype(np.float32)
    m = np.asarray(mask).astype(np.float32)[..., None]
    bg = np.asarray(background, dtype=np.float32)
    return img * m + bg * (1.0 - m)


@dataclass(frozen=True)
class EvalRegion:
    """Pixels a score is computed over."""

    mask: np.ndarray  # [H, W] bool: pixels counted by PSNR
    crop: tuple[int, int, int, int]  # (x0, y0, x1, y1), exclusive end: the SSIM crop

    def crop_image(self, img: np.ndarray) -> np.ndarray:
        x0, y0, x1, y1 = self.crop
        return img[y0:y1, x0:x1]


def box_corners(vertices: np.ndarray, pad: float = 0.05) -> np.ndarray:
    """[V, 3] posed vertices -> [8, 3] corners of their axis-aligned box, grown by `pad` metres (Neural Body: 0.05)."""
    lo = vertices.min(axis=0) - pad
    hi = vertices.max(axis=0) + pad
    return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])


def bbox_region(camera: Camera, vertices: np.ndarray, pad: float = 0.05) -> EvalRegion:
    """The `bbox` protocol's region for one (pinhole) camera and one frame's posed body vertices [V, 3]."""
    import cv2

    uv = camera.project(box_corners(np.asarray(vertices, dtype=np.float64), pad), distort=False)
    H, W = camera.height, camera.width
    hull = cv2.convexHull(np.round(uv).astype(np.int32))
    mask = np.zeros((H, W), np.uint8)
    cv2.fillConvexPoly(mask, hull, 1)
    x0 = int(np.clip(np.floor(uv[:, 0].min()), 0, W))
    x1 = int(np.clip(np.ceil(uv[:, 0].max()) + 1, 0, W))
    y0 = int(np.clip(np.floor(uv[:, 1].min()), 0, H))
    y1 = int(np.clip(np.ceil(uv[:, 1].max()) + 1, 0, H))
    return EvalRegion(mask=mask.astype(bool), crop=(x0, y0, x1, y1))


def full_region(height: int, width: int) -> EvalRegion:
    return EvalRegion(mask=np.ones((height, width), bool), crop=(0, 0, width, height))


def mpmavatar_weights(mask: np.ndarray) -> np.ndarray:
    """[H, W] bool ground-truth mask -> [H, W] float32 weights: eroded 5x by a 3x3 square, then a 5x5 Gaussian
    blur (sigma from the kernel size, as cv2 derives it for sigma 0)."""
    import cv2

    m = cv2.erode(np.asarray(mask, np.float32), np.ones((3, 3), np.uint8), iterations=5)
    return cv2.GaussianBlur(m, (5, 5), 0)


def mpmavatar_images(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray, white_cut: bool = True
                     ) -> tuple[np.ndarray, np.ndarray]:
    """([H, W, 3] float pred, [H, W, 3] float gt, [H, W] bool ground-truth mask) -> the two images MPMAvatar's
    eval.py scores: both times `mpmavatar_weights`, after, with `white_cut` (its ActorsHQ branch, the `mpmavatar`
    protocol), near-white pixels (mean > `WHITE_CUT`) of each zeroed; without (its 4D-DRESS branch,
    `mpmavatar_4d_dress`) the colours are kept."""
    w = mpmavatar_weights(mask)[..., None]
    out = []
    for img in (pred, gt):
        a = np.array(img, np.float32)
        if white_cut:
            a[a.mean(-1) > WHITE_CUT] = 0.0
        out.append(a * w)
    return out[0], out[1]
