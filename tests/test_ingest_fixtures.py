"""Small generated captures for the ingest tests (EasyMocap layout with an anny body), and checks of them.

`make_easymocap_capture` writes: intri/extri.yml (cameras with k1/k2 distortion), images/<cam>/%06d.jpg and
masks/<cam>/%06d.png rendered in the *distorted* geometry (mesh silhouette over a textured plate),
background/<cam>.png, motion.npz (anny `BodyMotion`). `RenderedCapture` keeps the ground truth.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from avatarctl.body.motion import BodyMotion
from avatarctl.geometry.cameras import Camera, look_at

BODY_RGB = np.array([205, 70, 60], np.uint8)


@dataclass
class RenderedCapture:
    root: Path
    cameras: list[Camera]  # distorted, as written to intri/extri.yml
    motion: BodyMotion
    frames: list[int]
    vertices: np.ndarray  # [frames, V, 3] posed mesh, world
    faces: np.ndarray  # [F, 3]


def ring_cameras(n: int = 3, size: int = 128, radius: float = 3.0, dist=(-0.08, 0.02, 0.0, 0.0, 0.0)) -> list[Camera]:
    cams = []
    for i in range(n):
        a = 2 * np.pi * i / n - np.pi / 2  # camera 0 in front of the subject (anny faces -y)
        eye = np.array([radius * np.cos(a), radius * np.sin(a), 0.1])
        R, T = look_at(eye, np.array([0.0, 0.0, -0.05]))
        f = size * 1.25
        K = np.array([[f, 0, (size - 1) / 2 + 1.5], [0, f * 1.01, (size - 1) / 2 - 1.0], [0, 0, 1]])
        cams.append(Camera(name=f"{i:02d}", K=K, R=R, T=T, width=size, height=size, dist=np.array(dist)))
    return cams


def plate(cam: Camera, seed: int) -> np.ndarray:
    """A smooth, textured background plate [H, W, 3] uint8 (colours far from BODY_RGB)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:cam.height, 0:cam.width].astype(np.float32)
    base = np.stack([60 + 40 * np.sin(xx / 9.0), 120 + 30 * np.cos(yy / 7.0), 150 + 25 * np.sin((xx + yy) / 11.0)], -1)
    return np.clip(base + rng.normal(0, 3, base.shape), 0, 255).astype(np.uint8)


def anny_motion(frames: list[int]) -> BodyMotion:
    from avatarctl.body.anny_model import identity_pose

    pp = identity_pose(len(frames))
    for i in range(len(frames)):  # a little heading and walk
        a = 0.3 * i
        pp[i, 0, :3, :3] = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
        pp[i, 0, :3, 3] = [0.05 * i, -0.03 * i, 0.0]
    return BodyMotion(body_model="anny", frame_index=np.array(frames), pose_parameters=pp)


def render(cam: Camera, verts: np.ndarray, faces: np.ndarray, bg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rgb, mask) in the distorted geometry of `cam` (small triangles: per-vertex distortion suffices)."""
    from avatarctl.ingest.silhouette import rasterize_silhouette

    sil = rasterize_silhouette(cam, verts, faces)  # cam.project applies the distortion
    rgb = bg.copy()
    yy = np.mgrid[0:cam.height, 0:cam.width][0]
    shade = (0.8 + 0.2 * yy / cam.height)[..., None]
    rgb[sil] = np.clip(BODY_RGB[None, None] * shade, 0, 255).astype(np.uint8)[sil]
    return rgb, sil


def make_easymocap_capture(root: Path, frames: list[int] = (0, 1, 2, 3), n_cams: int = 3, size: int = 128,
                           masks: bool = True, backgrounds: bool = True) -> RenderedCapture:
    import cv2

    from avatarctl.body.anny_model import AnnyBody
    from avatarctl.io.easymocap import write_easymocap_cameras

    frames = list(frames)
    root.mkdir(parents=True, exist_ok=True)
    cams = ring_cameras(n_cams, size)
    write_easymocap_cameras(root, cams)
    motion = anny_motion(frames)
    motion.save(root / "motion.npz")
    body = AnnyBody()
    verts = body.pose(motion).vertices.numpy()
    faces = body.faces().numpy()
    for ci, cam in enumerate(cams):
        bg = plate(cam, ci)
        if backgrounds:
            (root / "background").mkdir(exist_ok=True)
            cv2.imwrite(str(root / "background" / f"{cam.name}.png"), bg[..., ::-1])
        for k, f in enumerate(frames):
            rgb, sil = render(cam, verts[k], faces, bg)
            (root / "images" / cam.name).mkdir(parents=True, exist_ok=True)
            # 4:4:4 JPEG: with chroma subsampling, the saturated flat-red body bleeds ~2 px of colour into the
            # plate, which no real (blurred, textured) capture does to this extent
            cv2.imwrite(str(root / "images" / cam.name / f"{f:06d}.jpg"), rgb[..., ::-1],
                        [cv2.IMWRITE_JPEG_QUALITY, 95, cv2.IMWRITE_JPEG_SAMPLING_FACTOR,
                         cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444])
            if masks:
                (root / "masks" / cam.name).mkdir(parents=True, exist_ok=True)
                cv2.imwrite(str(root / "masks" / cam.name / f"{f:06d}.png"), sil.astype(np.uint8) * 255)
    return RenderedCapture(root, cams, motion, frames, verts, faces)


@pytest.mark.anny
def test_fixture_capture_is_easymocap_with_a_visible_body(tmp_path):
    from avatarctl.io.detect import detect_format

    cap = make_easymocap_capture(tmp_path / "cap", frames=[0], n_cams=2)
    assert detect_format(cap.root)[0] == "easymocap"
    import cv2

    m = cv2.imread(str(cap.root / "masks" / "00" / "000000.png"), cv2.IMREAD_GRAYSCALE)
    frac = (m > 0).mean()
    assert 0.02 < frac < 0.5, frac  # the body is in view and not filling the frame
