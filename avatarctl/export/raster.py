"""Render an exported `ColouredMesh` through a project camera: one ray per pixel centre, cast against the triangles
(`geometry.raycast.RayCaster`, Warp's BVH), the hit face's vertex colours interpolated barycentrically, unlit (the
colours are baked radiance, as the volume render shows them), composited over a background colour.

Conventions: pinhole camera (OpenCV, world->camera, metres), pixel centres at integer coordinates, the mesh in the
same world frame as the camera. The mesh's PSNR against held-out views (`stages/export.py --score`) is computed on
these images with the one metrics module, beside the volume render of the same (frame, view); `export.level` scores
candidate surface levels on training views with `cast_pixels` + `shade` (one ray cast per mesh and view, the colours
of only the vertices hit).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from avatarctl.export.mesh import ColouredMesh
from avatarctl.geometry.cameras import Camera

if TYPE_CHECKING:
    from avatarctl.geometry.raycast import RayCaster


@dataclass(frozen=True)
class MeshImage:
    rgb: np.ndarray  # [H, W, 3] float32 in [0, 1], over the background
    alpha: np.ndarray  # [H, W] float32, 1 where a triangle is hit


def barycentric(points: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Barycentric coordinates [points, 3] of points [points, 3] in triangles (a, b, c) [points, 3] each."""
    v0, v1, v2 = b - a, c - a, points - a
    d00, d01, d11 = (v0 * v0).sum(-1), (v0 * v1).sum(-1), (v1 * v1).sum(-1)
    d20, d21 = (v2 * v0).sum(-1), (v2 * v1).sum(-1)
    den = d00 * d11 - d01 * d01
    den = np.where(np.abs(den) < 1e-30, 1e-30, den)
    v = (d11 * d20 - d01 * d21) / den
    w = (d00 * d21 - d01 * d20) / den
    return np.stack([1.0 - v - w, v, w], axis=-1)


def render_mesh(mesh: ColouredMesh, camera: Camera, background: tuple[float, float, float]) -> MeshImage:
    """The mesh seen by `camera` (module docstring)."""
    from avatarctl.geometry.raycast import RayCaster

    return shade(mesh, cast_pixels(RayCaster(mesh.vertices, mesh.faces), camera), background)


@dataclass(frozen=True)
class MeshHits:
    """The pixels of one camera whose ray hits the mesh: what `shade` needs, and the faces (hence the vertices) whose
    colours show in the image (`export.level` bakes only those)."""

    pixel: np.ndarray  # [hits] int64, flat pixel index (row-major, H * W)
    face: np.ndarray  # [hits] int64, the face hit
    points: np.ndarray  # [hits, 3] float64, the hit points (world, metres)
    height: int
    width: int


def cast_pixels(caster: "RayCaster", camera: Camera) -> MeshHits:
    """One ray per pixel centre of the pinhole `camera` cast against `caster`'s triangles (`geometry.raycast.RayCaster`,
    built once per mesh and reused for every camera)."""
    from avatarctl.synth.raster import camera_rays

    grid = camera_rays(camera.pinhole())
    H, W = grid.dirs.shape[:2]
    dirs = grid.dirs.reshape(-1, 3)
    face, t = caster.cast(grid.origin, dirs)
    hit = np.flatnonzero(face >= 0)
    points = grid.origin[None].astype(np.float64) + t[hit, None].astype(np.float64) * dirs[hit].astype(np.float64)
    return MeshHits(pixel=hit, face=face[hit].astype(np.int64), points=points, height=H, width=W)


def shade(mesh: ColouredMesh, hits: MeshHits, background: tuple[float, float, float]) -> MeshImage:
    """The image of `hits`: the hit face's vertex colours interpolated barycentrically at the hit point, unlit, over
    `background` where no face is hit."""
    H, W = hits.height, hits.width
    rgb = np.empty((H * W, 3), np.float32)
    rgb[:] = np.asarray(background, np.float32)
    if hits.pixel.size:
        tri = mesh.faces[hits.face]  # [hits, 3]
        v = mesh.vertices.astype(np.float64)
        bc = np.clip(barycentric(hits.points, v[tri[:, 0]], v[tri[:, 1]], v[tri[:, 2]]), 0.0, 1.0)
        bc /= np.maximum(bc.sum(-1, keepdims=True), 1e-12)
        rgb[hits.pixel] = (bc[..., None] * mesh.colours[tri]).sum(1)
    alpha = np.zeros(H * W, np.float32)
    alpha[hits.pixel] = 1.0
    return MeshImage(rgb=np.clip(rgb, 0.0, 1.0).reshape(H, W, 3), alpha=alpha.reshape(H, W))
