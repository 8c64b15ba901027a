"""Score regions inside the protocol's pixels (`avatarctl eval --region`). Two splits, each of which covers the
protocol's region exactly (its two parts add up to "all"):

- garment / body: needs ground-truth geometry (`io.gt_geometry`, written by `avatarctl synth`). For one camera and
  frame the body and garment meshes are drawn together, far triangles first (painter's algorithm on the triangle
  centroid depth), so an arm in front of the skirt counts as body and the skirt behind a leg as nothing. The garment
  region is the pixels whose nearest surface is the garment, grown by `GROW_PX` pixels so its silhouette edge (where
  most of a blurry render's error sits) counts as garment; "body" is the rest of the protocol's region (body, face,
  hands and the background inside the box).
- edge / inner: any capture (its masks only). "edge" is the pixels within `EDGE_PX` of the ground-truth mask's
  boundary, on either side (the mask dilated minus the mask eroded, a (2 EDGE_PX + 1)-square kernel): where a
  render's silhouette and the mask's disagree, and where a supersampled or real image mixes the subject with what
  is behind it; "inner" is the rest (the subject inside that band, and the background beyond it).
"""

from __future__ import annotations

import numpy as np

from avatarctl.geometry.cameras import Camera

REGIONS = ("all", "garment", "body", "edge", "inner")  # all = the protocol's whole region (the box for bbox)
GEOMETRY_REGIONS = ("garment", "body")  # need the capture's ground-truth geometry
SILHOUETTE_REGIONS = ("edge", "inner")  # need only its masks
GROW_PX = 1
EDGE_PX = 1
_SHIFT = 4  # cv2 sub-pixel bits


def garment_mask(cam: Camera, body_vertices: np.ndarray, body_faces: np.ndarray, garment_vertices: np.ndarray,
                 garment_faces: np.ndarray) -> np.ndarray:
    """[H, W] bool: pixels of the (pinhole) camera `cam` whose nearest surface is the garment, grown by `GROW_PX`."""
    import cv2

    verts = np.concatenate([body_vertices, garment_vertices]).astype(np.float64)
    faces = np.concatenate([body_faces, garment_faces + len(body_vertices)])
    label = np.concatenate([np.full(len(body_faces), 1, np.uint8), np.full(len(garment_faces), 2, np.uint8)])
    depth = cam.world_to_camera(verts)[:, 2]
    uv = cam.project(verts)
    keep = (depth[faces] > 1e-3).all(axis=1)
    faces, label = faces[keep], label[keep]
    order = np.argsort(-depth[faces].mean(axis=1), kind="stable")  # far first
    pts = np.clip(np.round(uv[faces[order]] * (1 << _SHIFT)), -(1 << 28), 1 << 28).astype(np.int32)
    out = np.zeros((cam.height, cam.width), np.uint8)
    for tri, lab in zip(pts, label[order]):
        cv2.fillConvexPoly(out, tri, int(lab), cv2.LINE_8, _SHIFT)
    garment = (out == 2).astype(np.uint8)
    if GROW_PX:
        k = 2 * GROW_PX + 1
        garment = cv2.dilate(garment, np.ones((k, k), np.uint8))
    return garment.astype(bool)


def split_region(region_mask: np.ndarray, garment: np.ndarray) -> dict[str, np.ndarray]:
    """{"all": region, "garment": region & garment, "body": region & ~garment} ([H, W] bool each)."""
    return {"all": region_mask, "garment": region_mask & garment, "body": region_mask & ~garment}


def silhouette_band(mask: np.ndarray, px: int = EDGE_PX) -> np.ndarray:
    """[H, W] bool: the pixels within `px` of the boundary of `mask` ([H, W] bool), on either side (the image's own
    border is not a boundary; `geometry.silhouette.outline_band`, the rule the fit's image loss leaves out too)."""
    from avatarctl.geometry.silhouette import outline_band

    return outline_band(np.asarray(mask), px).numpy()


def split_silhouette(region_mask: np.ndarray, band: np.ndarray) -> dict[str, np.ndarray]:
    """{"all": region, "edge": region & band, "inner": region & ~band} ([H, W] bool each)."""
    return {"all": region_mask, "edge": region_mask & band, "inner": region_mask & ~band}
