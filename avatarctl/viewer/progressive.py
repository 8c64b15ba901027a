"""Progressive rendering for an interactive viewer, independent of any web framework.

`ProgressiveRenderer` runs one worker thread per client. Each `update(request)` (the camera moved, a slider changed)
bumps a version; the worker renders the newest request at `preview_scale` of the resolution at once, and, when no
update has come for `settle_s` seconds, renders it again at full resolution. A full-resolution render in progress
is abandoned as soon as a newer request arrives (the render callback receives a `should_stop()` it polls between
ray chunks), so a slow render on a CPU never holds the camera back; a preview is always finished and shown (then
the newest request is previewed next), so a continuous stream of requests — a drag, play — still shows images.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, replace
from typing import Callable

import numpy as np


@dataclass(frozen=True)
class ViewRequest:
    """What one viewer image shows: a camera pose and what the avatar does."""

    wxyz: tuple[float, float, float, float]  # camera-to-world rotation, quaternion (w, x, y, z), OpenCV axes
    position: tuple[float, float, float]  # camera centre, world, metres
    fov_y: float  # vertical field of view, radians
    aspect: float  # width / height
    frame: int  # position in the viewer's frame list
    latent: str  # auto | mean | zero | sample
    resolution: int  # longer image side at full quality, pixels


class Cancelled(Exception):
    """A render abandoned because a newer request arrived."""


RenderFn = Callable[[ViewRequest, Callable[[], bool]], np.ndarray]  # (request at its resolution, should_stop) -> image
ShowFn = Callable[[np.ndarray, ViewRequest, bool], None]  # (image [H, W, 3] uint8, request, full quality?)


class ProgressiveRenderer:
    """Low resolution while the view changes, full resolution once it has been still for `settle_s`."""

    def __init__(self, render: RenderFn, show: ShowFn, preview_scale: float = 0.25, settle_s: float = 0.3,
                 on_error: Callable[[BaseException], None] | None = None):
        if not 0 < preview_scale <= 1:
            raise ValueError(f"preview_scale must be in (0, 1], got {preview_scale}")
        self._render, self._show, self._on_error = render, show, on_error
        self.preview_scale, self.settle_s = float(preview_scale), float(settle_s)
        self._cond = threading.Condition()
        self._request: ViewRequest | None = None
        self._version = 0
        self._changed_at = 0.0
        self._stopped = False
        self.frames_shown: list[tuple[int, bool, float]] = []  # (version, full?, seconds) of every image shown
        self._thread = threading.Thread(target=self._loop, name="avatarctl-viewer-render", daemon=True)
        self._thread.start()

    def update(self, request: ViewRequest) -> None:
        with self._cond:
            self._request = request
            self._version += 1
            self._changed_at = time.monotonic()
            self._cond.notify_all()

    def stop(self, timeout: float = 5.0) -> None:
        with self._cond:
            self._stopped = True
            self._cond.notify_all()
        self._thread.join(timeout)

    def _loop(self) -> None:
        shown_version, shown_full = 0, True
        while True:
            with self._cond:
                while not self._stopped:
                    if self._version != shown_version:
                        break
                    if not shown_full:
                        wait = self.settle_s - (time.monotonic() - self._changed_at)
                        if wait <= 0:
                            break
                        self._cond.wait(wait)
                    else:
                        self._cond.wait()
                if self._stopped:
                    return
                version, request = self._version, self._request
                full = version == shown_version  # nothing new: the settle time passed -> full quality
            assert request is not None
            target = request if full else replace(
                request, resolution=max(16, int(round(request.resolution * self.preview_scale))))
            t0 = time.perf_counter()
            # a full render is abandoned by any newer request; a preview only by stop(), so that a stream of
            # requests (a drag, play) still shows previews at the rate they can be made
            should_stop = (lambda: self._version != version or self._stopped) if full else (lambda: self._stopped)
            try:
                image = self._render(target, should_stop)
            except Cancelled:
                continue
            except Exception as e:  # noqa: BLE001 - reported to the viewer, the loop keeps serving
                if self._on_error is not None:
                    self._on_error(e)
                shown_version, shown_full = version, True
                continue
            if full and self._version != version:  # stale by the time it finished: the newer request comes next
                continue
            self._show(image, request, full)
            self.frames_shown.append((version, full, time.perf_counter() - t0))
            shown_version, shown_full = version, full
