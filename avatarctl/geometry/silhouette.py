"""Projected body-mesh silhouettes (the seed for background matting, the contact-sheet overlay, the hull-node carve),
and the band along a mask's outline."""

from __future__ import annotations

import numpy as np

from avatarctl.geometry.cameras import Camera

_SHIFT = 4  # cv2.fillPoly sub-pixel bits


def project_vertices(cam: Camera, vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """[V, 3] world vertices -> ([V, 2] pixels in the (pinhole) camera, [V] bool in front of the camera)."""
    Xc = cam.world_to_camera(np.asarray(vertices, dtype=np.float64))
    return cam.project(vertices), Xc[:, 2] > 1e-3


def rasterize_silhouette(cam: Camera, vertices: np.ndarray, faces: np.ndarray, supersample: int = 4) -> np.ndarray:
    """bool [H, W]: pixels at least half covered by the mesh (`vertices` [V, 3] world, `faces` [F, 3]) seen by
    `cam`. Triangles are filled at `supersample` x resolution (cv2 fills every pixel an edge touches, a bias of
    half a sample), then averaged down: coverage >= 0.5."""
    import cv2

    uv, front = project_vertices(cam, vertices)
    tri = faces[front[faces].all(axis=1)]
    ss = int(supersample)
    # pixel centre (x, y) covers [x - 0.5, x + 0.5]; sample centre i at supersampled (i + 0.5) / ss - 0.5
    pts = np.round(((uv[tri] + 0.5) * ss - 0.5) * (1 << _SHIFT)).astype(np.int64)  # [F, 3, 2]
    pts = np.clip(pts, -(1 << 28), 1 << 28).astype(np.int32)
    out = np.zeros((cam.height * ss, cam.width * ss), dtype=np.uint8)
    for t in pts:  # one call per triangle: fillPoly with many polygons fills overlaps even-odd (holes)
        cv2.fillConvexPoly(out, t, 255, cv2.LINE_8, _SHIFT)
    if ss > 1:
        out = cv2.resize(out, (cam.width, cam.height), interpolation=cv2.INTER_AREA)
    return out >= 128


def fraction_inside(cam: Camera, vertices: np.ndarray, mask: np.ndarray, tolerance_px: int = 1) -> float:
    """Fraction of the `vertices` [V, 3] whose projection (nearest pixel) falls inside the foreground `mask`
    [H, W] grown by `tolerance_px` (a vertex on the silhouette edge lands in a boundary pixel whose coverage
    may be < 50 %: at 96 px, ~10 % of a body's vertices do, so 0 tolerance measures resolution, not alignment)."""
    import cv2

    if tolerance_px:
        k = 2 * tolerance_px + 1
        mask = cv2.dilate(mask.astype(np.uint8), np.ones((k, k), np.uint8)) > 0
    uv, front = project_vertices(cam, vertices)
    px = np.round(uv).astype(np.int64)
    ok = front & (px[:, 0] >= 0) & (px[:, 0] < cam.width) & (px[:, 1] >= 0) & (px[:, 1] < cam.height)
    inside = np.zeros(len(px), dtype=bool)
    inside[ok] = mask[px[ok, 1], px[ok, 0]]
    return float(inside.mean()) if len(px) else 0.0


def outline_band(mask, px: int):
    """bool [H, W] torch tensor (on `mask`'s device): the pixels within `px` of the outline of `mask` ([H, W] tensor
    or array, foreground > 0.5), on either side: the mask grown minus the mask shrunk by a (2 px + 1)-square window;
    the image's own border is no outline. The one rule of the image loss's left-out outline
    (`model.losses.mask_border_weight`) and eval's edge region (`evaluate.regions.silhouette_band`)."""
    import torch

    m = (torch.as_tensor(mask).to(torch.float32) > 0.5).to(torch.float32)[None, None]
    k = 2 * px + 1
    grown = torch.nn.functional.max_pool2d(m, k, stride=1, padding=px)
    shrunk = -torch.nn.functional.max_pool2d(-m, k, stride=1, padding=px)
    return (grown > shrunk)[0, 0]
