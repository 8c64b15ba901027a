"""A tiny ingested project for the fit / render-engine tests (and a test that the fixture itself is sane).

`make_tiny_project(root)`: the anny body in its reference pose (3 frames, the root translated a little per frame),
seen by 4 cameras on a ring at `size` px; images painted with the painter's algorithm (faces coloured by their
canonical position), masks = the projected mesh. Cameras 0, 2 train; 1, 3 are held out. No licensed data.
"""

from __future__ import annotations

import numpy as np
import pytest

from avatarctl.body.motion import BodyMotion
from avatarctl.project import BodyModelRef, Project, SourceRef
from avatarctl.geometry.cameras import Camera, look_at


def ring_cameras(n: int, size: int, radius: float = 2.6, height: float = 0.0) -> list[Camera]:
    f = size * 1.6
    K = np.array([[f, 0, (size - 1) / 2], [0, f, (size - 1) / 2], [0, 0, 1]])
    cams = []
    for i in range(n):
        a = 2 * np.pi * i / n - np.pi / 2  # camera 0 in front of the subject (anny faces -y)
        eye = np.array([radius * np.cos(a), radius * np.sin(a), height])
        R, T = look_at(eye, np.array([0.0, 0.0, -0.1]))
        cams.append(Camera(name=f"cam{i:02d}", K=K, R=R, T=T, width=size, height=size))
    return cams


def paint(cam: Camera, verts: np.ndarray, faces: np.ndarray, colours: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Painter's algorithm: far faces first. -> (rgb uint8 [H, W, 3], mask bool [H, W])."""
    import cv2

    uv = cam.project(verts, distort=False)
    depth = cam.world_to_camera(verts)[:, 2]
    order = np.argsort(-depth[faces].mean(1))
    scale = 8  # sub-pixel precision for cv2.fillPoly
    img = np.zeros((cam.height, cam.width, 3), np.uint8)
    pts = np.round(uv * scale).astype(np.int32)
    for fi in order:
        cv2.fillConvexPoly(img, pts[faces[fi]], colours[fi].tolist(), lineType=cv2.LINE_8, shift=3)
    mask = np.zeros((cam.height, cam.width), np.uint8)
    cv2.fillPoly(mask, [pts[f] for f in faces], 1, lineType=cv2.LINE_8, shift=3)
    return img, mask.astype(bool)


def make_tiny_project(root, size: int = 40, frames: int = 3, cams: int = 4) -> Project:
    from avatarctl.body.anny_model import identity_pose
    from avatarctl.body.registry import load_body_model
    from avatarctl.io.project_io import Split, save_cameras, save_split, write_frame, write_mask

    pose = identity_pose(frames)
    pose[:, 0, 0, 3] = np.linspace(-0.03, 0.03, frames)  # root translation along x per frame
    motion = BodyMotion(body_model="anny", frame_index=np.arange(frames), fps=30.0, pose_parameters=pose)
    project = Project.create(root, body_model=BodyModelRef(name="anny", path=None),
                             source=SourceRef(path="test", format="synthetic", sha256="", files=0))
    body = load_body_model("anny")
    template = body.template(motion)
    posed = body.pose(motion)
    faces = template.faces.numpy()
    cv = template.vertices.numpy()[faces].mean(1)  # [F, 3] canonical face centres -> colours
    lo, hi = cv.min(0), cv.max(0)
    colours = (40 + 200 * (cv - lo) / (hi - lo)).astype(np.uint8)
    colours = np.where((np.floor(cv[:, 2:3] * 10) % 2) == 0, colours, colours[:, ::-1])  # stripes
    cameras = ring_cameras(cams, size)
    save_cameras(project.paths.cameras, cameras)
    for f in range(frames):
        verts = posed.vertices[f].numpy().astype(np.float64)
        for cam in cameras:
            img, mask = paint(cam, verts, faces, colours)
            write_frame(project, cam.name, f, img)
            write_mask(project, cam.name, f, mask)
    motion.save(project.paths.body)
    names = [c.name for c in cameras]
    save_split(project.paths.split, Split(train_frames=list(range(frames)), test_frames=[],
                                          train_views=names[0::2], test_views=names[1::2]))
    project.record("ingest", {"test": True}, [project.paths.cameras, project.paths.body, project.paths.split],
                   started="test")
    return project


@pytest.mark.anny
def test_tiny_project_images_show_the_body(tmp_path):
    from avatarctl.io.project_io import load_project_capture

    cap = load_project_capture(make_tiny_project(tmp_path / "p", size=32, frames=1, cams=2))
    for cam in cap.cameras:
        img, mask = cap.image(cam, 0), cap.mask(cam, 0)
        assert img.shape == (32, 32, 3) and mask.shape == (32, 32)
        assert 0.05 < mask.mean() < 0.6, f"{cam}: body covers {mask.mean():.2f} of the image"
        assert img[~mask].mean() < 5 and img[mask].mean() > 40  # black outside (JPEG ringing aside), painted inside
