"""What the interactive viewer shows of one fitted avatar, per (frame, latent):

- `render(request)`: the exact image (`render.engine.render_view`, the renderer of `render` and `eval`: ray-marched
  for the SLRF fields, rasterized for the Gaussian local fields), at the request's camera and resolution;
- `splats(frame, latent)` (Gaussian local fields only): the frame's posed Gaussians as arrays a browser splat
  renderer draws and orbits by itself (`viewer.splats.SplatFrame`; node transforms, Delta n and the per-node
  decoder: milliseconds on the CPU), posed on each call (the controller caches the encoded frames:
  `viewer.controller.FrameCache`);
- `mesh(frame, latent)`: a posed mesh from the `MeshFn` callback the stage gives (for the ray-marched fields: drawn by
  the page while the progressive render refines), or None without one.

A session plays one `ViewerMotion` at a time (the project's frames, or a motion file's); `set_motion` switches to
another one (loaded by the stage's `MotionLoader`) and empties the node-state cache.

Camera convention: the viewer's camera follows OpenCV axes (x right, y down, z forward, as viser does); `wxyz` is
the camera-to-world rotation and `position` the camera centre, so the world->camera `Camera` has R = R_wc^T and
T = -R position. A pinhole with square pixels, principal point at the image centre, focal length from the vertical
field of view: f = (H / 2) / tan(fov_y / 2). The session knows nothing of projects: the node state of a frame comes
from a callback (`StateFn`, the stage's `frame_node_state`).
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

from avatarctl.geometry.cameras import Camera
from avatarctl.progress import ProgressReport
from avatarctl.viewer.progressive import Cancelled, ViewRequest

if TYPE_CHECKING:
    from avatarctl.model.avatar import NodeState, SlrfAvatar
    from avatarctl.viewer.splats import SplatFrame


@dataclass(frozen=True)
class ViewerFrame:
    """One entry of the viewer's frame slider."""

    label: str  # e.g. "frame 12 (train)"
    frame: int  # frame number (project capture frame or motion-file frame)
    source: str  # "train" | "test" | "motion"


StateFn = Callable[[int, str], "NodeState"]  # (position in the frame list, latent mode) -> NodeState of one frame
MeshFn = Callable[["NodeState"], Any]  # NodeState of one frame -> a mesh with vertices [V, 3], faces [F, 3], colors


@dataclass(frozen=True)
class ViewerMotion:
    """A frame list the viewer plays: its name in the page, its frames, their node states, its frame rate."""

    name: str  # "project" or the motion file's path
    frames: list[ViewerFrame]
    state_fn: StateFn
    fps: float  # frames per second of the motion (play speed)
    note: str | None = None  # e.g. what retargeting did, shown in the page


MotionLoader = Callable[[str], ViewerMotion]  # a motion file's path -> its ViewerMotion (raises with a one-line error)


def quaternion_wxyz_to_matrix(wxyz: tuple[float, float, float, float]) -> np.ndarray:
    """(w, x, y, z) -> [3, 3] rotation."""
    w, x, y, z = (float(c) for c in wxyz)
    n = np.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / n, x / n, y / n, z / n
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def matrix_to_quaternion_wxyz(R: np.ndarray) -> tuple[float, float, float, float]:
    """[3, 3] rotation -> (w, x, y, z), w >= 0 (the inverse of `quaternion_wxyz_to_matrix`)."""
    R = np.asarray(R, np.float64)
    t = np.trace(R)
    if t > 0:
        s = 2.0 * np.sqrt(t + 1.0)
        q = (0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s)
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(max(1.0 + R[i, i] - R[j, j] - R[k, k], 1e-12))
        v = [0.0, 0.0, 0.0]
        v[i], v[j], v[k] = 0.25 * s, (R[j, i] + R[i, j]) / s, (R[k, i] + R[i, k]) / s
        q = ((R[k, j] - R[j, k]) / s, *v)
    q = np.asarray(q) / np.linalg.norm(q)
    q = -q if q[0] < 0 else q
    return (float(q[0]), float(q[1]), float(q[2]), float(q[3]))


def request_camera(req: ViewRequest) -> Camera:
    """The pinhole `Camera` of a request at its resolution (longer side = `req.resolution`; module docstring)."""
    aspect = max(float(req.aspect), 1e-3)
    if aspect >= 1:
        W, H = int(req.resolution), max(1, int(round(req.resolution / aspect)))
    else:
        W, H = max(1, int(round(req.resolution * aspect))), int(req.resolution)
    f = (H / 2.0) / np.tan(float(req.fov_y) / 2.0)
    K = np.array([[f, 0, (W - 1) / 2.0], [0, f, (H - 1) / 2.0], [0, 0, 1]])
    R_wc = quaternion_wxyz_to_matrix(req.wxyz)
    R = R_wc.T
    return Camera(name="viewer", K=K, R=R, T=-R @ np.asarray(req.position, np.float64), width=W, height=H)


class ViewerSession:
    """Renders `ViewRequest`s of one fitted avatar (`render` is the `ProgressiveRenderer` callback), and gives the
    posed Gaussians (`splats`) or a posed mesh (`mesh`) of a frame for the browser to draw. Thread-safe: one lock
    serialises every model call (one model, one device)."""

    def __init__(self, model: "SlrfAvatar", motion: ViewerMotion, background: tuple[float, float, float],
                 max_rays_per_chunk: int = 4096, cache: int = 8, load_motion: MotionLoader | None = None,
                 mesh_fn: MeshFn | None = None):
        if not motion.frames:
            raise ValueError("the viewer needs at least one frame")
        self.model, self.motion = model, motion
        self.background = tuple(float(c) for c in background)
        self.max_rays = int(max_rays_per_chunk)
        self.load_motion, self.mesh_fn = load_motion, mesh_fn
        self.lock = threading.RLock()
        self._states: OrderedDict[tuple[int, str], "NodeState"] = OrderedDict()
        self._cache = int(cache)
        self.last_seconds = 0.0

    @property
    def frames(self) -> list[ViewerFrame]:
        return self.motion.frames

    @property
    def gaussian(self) -> bool:
        """True for the Gaussian local fields (the page draws splats), False for the ray-marched fields."""
        return self.model.field_kind.splats

    def set_motion(self, name: str) -> ViewerMotion:
        """Play another motion (the stage's loader; its errors pass through); empties the node-state cache."""
        if self.load_motion is None:
            raise ValueError("this viewer has no motion loader")
        motion = self.load_motion(name)
        if not motion.frames:
            raise ValueError(f"motion {name} has no frames")
        with self.lock:
            self.motion = motion
            self._states.clear()
        return motion

    def _check(self, frame: int) -> None:
        if not 0 <= frame < len(self.frames):
            raise IndexError(f"frame position {frame} outside the viewer's {len(self.frames)} frames")

    def state(self, frame: int, latent: str) -> "NodeState":
        key = (int(frame), latent)
        with self.lock:
            if key not in self._states:
                self._states[key] = self.motion.state_fn(int(frame), latent)
                while len(self._states) > self._cache:
                    self._states.popitem(last=False)
            self._states.move_to_end(key)
            return self._states[key]

    def splats(self, frame: int, latent: str) -> "SplatFrame":
        """The posed Gaussians of a frame for a browser splat renderer (Gaussian local fields only), posed now."""
        import torch

        from avatarctl.viewer.splats import splat_frame

        if not self.gaussian:
            raise ValueError("splats need a Gaussian-field avatar (model.field = 'gaussians')")
        self._check(frame)
        with self.lock, torch.no_grad():
            return splat_frame(self.model.posed_gaussians(self.state(frame, latent)), 0)

    def mesh(self, frame: int, latent: str) -> Any:
        """The mesh of `mesh_fn` for a frame, or None without one (not cached: the page keeps what it was sent)."""
        if self.mesh_fn is None:
            return None
        self._check(frame)
        with self.lock:
            return self.mesh_fn(self.state(frame, latent))

    def render(self, req: ViewRequest, should_stop: Callable[[], bool] = lambda: False) -> np.ndarray:
        """[H, W, 3] uint8 image of the request (raises `Cancelled` when `should_stop()` turns true)."""
        from avatarctl.render.engine import render_view
        from avatarctl.render.images import to_uint8

        self._check(req.frame)
        with self.lock:
            t0 = time.perf_counter()
            state = self.state(req.frame, req.latent)

            def progress(report: ProgressReport) -> None:
                if should_stop():
                    raise Cancelled()

            view = render_view(self.model, state, 0, request_camera(req), self.background,
                               max_rays_per_chunk=self.max_rays, progress=progress)
            self.last_seconds = time.perf_counter() - t0
        return to_uint8(view.rgb)
