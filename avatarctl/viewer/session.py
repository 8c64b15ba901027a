"""The render callback of the interactive viewer: a `ViewRequest` (camera pose, frame, latent mode, resolution) ->
an RGB image of the avatar, with the node state of each (frame, latent) cached.

Camera convention: the viewer's camera follows OpenCV axes (x right, y down, z forward, as viser does); `wxyz` is
the camera-to-world rotation and `position` the camera centre, so the world->camera `Camera` has R = R_wc^T and
T = -R position. A pinhole with square pixels, principal point at the image centre, focal length from the vertical
field of view: f = (H / 2) / tan(fov_y / 2). The session knows nothing of projects: the node state of a frame comes
from a callback (`StateFn`, the stage's `frame_node_state`).
"""

from __future__ import annotations

import time
from collections import OrderedDict
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable

import numpy as np

from avatarctl.geometry.cameras import Camera
from avatarctl.viewer.progressive import Cancelled, ViewRequest

if TYPE_CHECKING:
    from avatarctl.model.avatar import NodeState, SlrfAvatar


@dataclass(frozen=True)
class ViewerFrame:
    """One entry of the viewer's frame slider."""

    label: str  # e.g. "frame 12 (train)"
    frame: int  # frame number (project capture frame or motion-file frame)
    source: str  # "train" | "test" | "motion"


StateFn = Callable[[int, str], "NodeState"]  # (position in the frame list, latent mode) -> NodeState of one frame


def quaternion_wxyz_to_matrix(wxyz: tuple[float, float, float, float]) -> np.ndarray:
    """(w, x, y, z) -> [3, 3] rotation."""
    w, x, y, z = (float(c) for c in wxyz)
    n = np.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / n, x / n, y / n, z / n
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


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
    """Renders `ViewRequest`s of one fitted avatar (`render` is the `ProgressiveRenderer` callback)."""

    def __init__(self, model: "SlrfAvatar", frames: list[ViewerFrame], state_fn: StateFn,
                 background: tuple[float, float, float], max_rays_per_chunk: int = 4096, cache: int = 8):
        if not frames:
            raise ValueError("the viewer needs at least one frame")
        self.model, self.frames, self.state_fn = model, frames, state_fn
        self.background = tuple(float(c) for c in background)
        self.max_rays = int(max_rays_per_chunk)
        self._states: OrderedDict[tuple[int, str], "NodeState"] = OrderedDict()
        self._cache = int(cache)
        self.last_seconds = 0.0

    def state(self, frame: int, latent: str) -> "NodeState":
        key = (int(frame), latent)
        if key not in self._states:
            self._states[key] = self.state_fn(int(frame), latent)
            while len(self._states) > self._cache:
                self._states.popitem(last=False)
        self._states.move_to_end(key)
        return self._states[key]

    def render(self, req: ViewRequest, should_stop: Callable[[], bool] = lambda: False) -> np.ndarray:
        """[H, W, 3] uint8 image of the request (raises `Cancelled` when `should_stop()` turns true)."""
        from avatarctl.render.engine import render_view
        from avatarctl.render.images import to_uint8

        if not 0 <= req.frame < len(self.frames):
            raise IndexError(f"frame position {req.frame} outside the viewer's {len(self.frames)} frames")
        t0 = time.perf_counter()
        state = self.state(req.frame, req.latent)

        def progress(done: int, total: int) -> None:
            if should_stop():
                raise Cancelled()

        view = render_view(self.model, state, 0, request_camera(req), self.background,
                           max_rays_per_chunk=self.max_rays, progress=progress)
        self.last_seconds = time.perf_counter() - t0
        return to_uint8(view.rgb)
