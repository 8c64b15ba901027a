"""What the viewer's controls do, once for every page: the state of the panel, play, posing, render, save video.

Two front-ends sit on one `ViewerController`: the viser page (`viewer.server.ViewerServer`, ray-marched avatars:
progressive server renders) and our own page (`viewer.splat_server.SplatPageServer`, Gaussian-field avatars: the
browser draws each frame's posed Gaussians). A front-end turns its widgets into the controller's setters
(`set_frame`, `set_playing`, `switch_motion`, ...) and shows what the controller reports:
- `subscribe(on_state)`: called with a `ViewState` after every change (frame, motion, status line, ...);
- `subscribe_frames(on_frame)` (Gaussian-field avatars): called from the posing thread with each newly posed
  frame's `SplatFrame`. One posing thread poses the newest (motion, frame, latent) asked for: a frame asked for while
  another is being posed replaces the one waiting (dropped, never queued). Callbacks must not block.

Play keeps wall-clock time at the motion's frame rate: when posing or drawing is slower, frames are skipped, never
slowed. "save video" starts the `VideoFn` the stage gives (`avatarctl render` in a child process) and reports its
progress in the status line. Thread-safe; callbacks run outside the controller's lock.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Callable, Protocol

import numpy as np

from avatarctl.viewer.progressive import ViewRequest

if TYPE_CHECKING:
    from avatarctl.viewer.session import ViewerSession
    from avatarctl.viewer.splats import SplatFrame

LATENTS = ("auto", "mean", "zero", "sample")
CAMERA_PATHS = ("held-out view", "orbit")


class VideoJob(Protocol):
    """A running "save video": `poll()` is None while it runs, then a one-line outcome; `cancel()` ends it."""

    def poll(self) -> str | None: ...

    def progress(self) -> str: ...

    def cancel(self) -> None: ...


VideoFn = Callable[[str, str, str], VideoJob]  # (motion name, latent mode, camera path) -> a started job


@dataclass(frozen=True)
class FrameKey:
    """Which posed frame: the motion shown (`generation` counts motion switches), its frame, the latent mode."""

    generation: int
    frame: int
    latent: str


@dataclass(frozen=True)
class ViewState:
    """The panel of every page (what a front-end shows)."""

    motion: str  # name of the motion shown ("project" or a motion file's path)
    motions: tuple[str, ...]  # the motions offered
    generation: int  # +1 at each motion switch
    labels: tuple[str, ...]  # one per frame of the motion, e.g. "frame 12 (train)"
    frame: int  # position in `labels`
    playing: bool
    fps: float  # play speed, frames per second
    latent: str  # one of LATENTS
    resolution: int  # longer side of a server render, pixels
    camera_path: str  # one of CAMERA_PATHS ("save video")
    status: str  # the status line (markdown-free text)
    gaussian: bool  # the page draws splats (else server renders)
    can_load: bool  # motion files can be loaded
    can_video: bool  # "save video" is available and not running

    @property
    def key(self) -> FrameKey:
        return FrameKey(self.generation, self.frame, self.latent)


class ViewerController:
    """The state of the viewer's controls and the work behind them (module docstring); `stop()` ends its threads."""

    def __init__(self, session: "ViewerSession", fps: float | None = None, latent: str = "auto",
                 resolution: int = 512, motions: tuple[str, ...] = (), video: VideoFn | None = None):
        if latent not in LATENTS:
            raise ValueError(f"latent {latent!r} not one of {LATENTS}")
        self.session, self.video_fn = session, video
        self._lock = threading.RLock()
        self._extra = ""
        self._fixed_fps = fps
        self._state = ViewState(
            motion=session.motion.name, motions=tuple(dict.fromkeys((session.motion.name, *motions))), generation=0,
            labels=tuple(f.label for f in session.frames), frame=0, playing=False,
            fps=float(fps or session.motion.fps), latent=latent, resolution=int(resolution),
            camera_path=CAMERA_PATHS[0], status="", gaussian=session.gaussian,
            can_load=session.load_motion is not None, can_video=video is not None)
        self._state = replace(self._state, status=self._status_text(self._state))
        self._state_cbs: list[Callable[[ViewState], None]] = []
        self._frame_cbs: list[Callable[[FrameKey, "SplatFrame"], None]] = []
        self._stop = threading.Event()
        self._wake = threading.Condition()
        self._video_job: VideoJob | None = None
        self._video_polled = 0.0
        self.posed: list[tuple[float, FrameKey]] = []  # (monotonic time, key) of every frame the posing thread made
        self._threads = [threading.Thread(target=self._play_loop, name="avatarctl-viewer-play", daemon=True)]
        if session.gaussian:
            self._threads.append(threading.Thread(target=self._pose_loop, name="avatarctl-viewer-pose", daemon=True))
        for th in self._threads:
            th.start()

    # ---- reading and subscribing -------------------------------------------------------------------------------
    @property
    def state(self) -> ViewState:
        return self._state

    def subscribe(self, on_state: Callable[[ViewState], None]) -> Callable[[], None]:
        """Call `on_state(state)` after each change; returns the function that unsubscribes."""
        with self._lock:
            self._state_cbs.append(on_state)
        return lambda: self._remove(self._state_cbs, on_state)

    def subscribe_frames(self, on_frame: Callable[[FrameKey, "SplatFrame"], None]) -> Callable[[], None]:
        """Call `on_frame(key, splats)` for each newly posed frame (Gaussian fields); asks for the current one."""
        with self._lock:
            self._frame_cbs.append(on_frame)
        self._want_pose()
        return lambda: self._remove(self._frame_cbs, on_frame)

    def _remove(self, table: list, cb: Callable) -> None:
        with self._lock:
            if cb in table:
                table.remove(cb)

    def latest_frame(self) -> tuple[FrameKey, "SplatFrame"]:
        """The current frame's splats, posed now if not cached (Gaussian fields)."""
        key = self._state.key
        return key, self.session.splats(key.frame, key.latent)

    # ---- changing the state ------------------------------------------------------------------------------------
    def _status_text(self, s: ViewState, extra: str = "") -> str:
        label = s.labels[min(s.frame, len(s.labels) - 1)]
        mode = "splats drawn by the page" if s.gaussian else "server render"
        note = f" · {self.session.motion.note}" if self.session.motion.note else ""
        return f"{label} · {mode}{note}" + (f"\n{extra}" if extra else "")

    def _update(self, extra: str | None = None, **changes) -> ViewState:
        """Apply `changes` (and a new status detail when `extra` is given), tell the subscribers if anything
        changed; returns the new state."""
        with self._lock:
            old = self._state
            if extra is not None:
                self._extra = extra
            new = replace(old, **changes)
            new = replace(new, status=self._status_text(new, self._extra))
            if new == old:
                return old
            self._state = new
            cbs = list(self._state_cbs)
        if new.key != old.key and new.gaussian:
            self._want_pose()
        for cb in cbs:
            cb(new)
        return new

    def set_status(self, extra: str) -> None:
        """The second line of the status (render time, errors, video progress)."""
        self._update(extra=extra)

    def set_frame(self, frame: int) -> None:
        n = len(self._state.labels)
        self._update(frame=int(min(max(int(frame), 0), n - 1)))

    def set_latent(self, latent: str) -> None:
        if latent not in LATENTS:
            self.set_status(f"unknown latent mode {latent!r} (one of {', '.join(LATENTS)})")
            return
        self._update(latent=latent)

    def set_playing(self, playing: bool) -> None:
        self._update(playing=bool(playing) and len(self._state.labels) > 1)

    def set_fps(self, fps: float) -> None:
        self._update(fps=float(min(max(float(fps), 0.5), 240.0)))

    def set_resolution(self, resolution: int) -> None:
        self._update(resolution=int(min(max(int(resolution), 16), 2048)))

    def set_camera_path(self, path: str) -> None:
        if path in CAMERA_PATHS:
            self._update(camera_path=path)

    def switch_motion(self, name: str, add: bool = False) -> None:
        """Play another motion (an offered one, or a motion file's path when `add`); errors go to the status line."""
        name = name.strip()
        if not name or (name == self._state.motion and not add):
            return
        self._update(playing=False, extra=f"loading {name} ...")
        try:
            motion = self.session.set_motion(name)
        except Exception as e:  # noqa: BLE001 - a one-line message in the page; the viewer keeps serving
            self.set_status(f"cannot load {name}: {e}")
            return
        s = self._state
        motions = s.motions if motion.name in s.motions else (*s.motions, motion.name)
        self._update(extra="", motion=motion.name, motions=motions, generation=s.generation + 1,
                     labels=tuple(f.label for f in motion.frames), frame=0,
                     fps=float(self._fixed_fps or motion.fps))

    def request(self, wxyz: tuple[float, float, float, float], position: tuple[float, float, float], fov_y: float,
                aspect: float, resolution: int | None = None) -> ViewRequest:
        """The `ViewRequest` of a camera (camera-to-world `wxyz`, centre `position`, OpenCV axes) at the current
        frame, latent and resolution."""
        s = self._state
        return ViewRequest(wxyz=tuple(float(c) for c in wxyz), position=tuple(float(c) for c in position),
                           fov_y=float(fov_y), aspect=float(aspect), frame=s.frame, latent=s.latent,
                           resolution=int(resolution or s.resolution))

    def render(self, req: ViewRequest) -> np.ndarray:
        """The exact image of a request ([H, W, 3] uint8; the renderer of `render` / `eval`); raises, with the
        status line set, when it fails."""
        self.set_status(f"rendering {req.resolution} px on the server ...")
        try:
            image = self.session.render(req)
        except Exception as e:
            self.set_status(f"render failed: {type(e).__name__}: {e}")
            raise
        self.set_status(f"exact render {image.shape[1]}x{image.shape[0]} · "
                        f"{self.session.last_seconds * 1000:.0f} ms (move the camera to orbit again)")
        return image

    def start_video(self) -> None:
        """Start "save video" for the motion, latent and camera path shown (one at a time)."""
        s = self._state
        if self.video_fn is None or self._video_job is not None:
            return
        try:
            self._video_job = self.video_fn(s.motion, s.latent, s.camera_path)
        except Exception as e:  # noqa: BLE001 - reported in the page
            self.set_status(f"save video failed: {e}")
            return
        self._update(can_video=False, extra="saving video: starting ...")

    # ---- threads -----------------------------------------------------------------------------------------------
    def _want_pose(self) -> None:
        with self._wake:
            self._wake.notify_all()

    def _pose_loop(self) -> None:
        """Pose the newest frame asked for and hand it to the frame subscribers (newest wins)."""
        done: FrameKey | None = None
        while True:
            with self._wake:
                while not self._stop.is_set() and (self._state.key == done or not self._frame_cbs):
                    self._wake.wait(0.5)
                if self._stop.is_set():
                    return
                key = self._state.key
            try:
                splats = self.session.splats(key.frame, key.latent)
            except Exception as e:  # noqa: BLE001 - reported in the page; the viewer keeps serving
                self.set_status(f"posing failed: {type(e).__name__}: {e}")
                done = key
                continue
            if key.generation != self._state.generation:  # the motion changed while posing: a stale frame
                continue
            done = key
            self.posed.append((time.monotonic(), key))
            del self.posed[:-1000]
            with self._lock:
                cbs = list(self._frame_cbs)
            for cb in cbs:
                cb(key, splats)

    def _play_loop(self) -> None:
        """While playing, the frame follows wall-clock time at the fps (frames skipped when drawing is slow)."""
        start: tuple[float, int, int] | None = None  # (time, frame, motion generation) when play started
        while not self._stop.wait(0.005 if start else 0.05):
            s = self._state
            if not (s.playing and len(s.labels) > 1):
                start = None
                self._poll_video()
                continue
            if start is None or start[2] != s.generation:
                start = (time.monotonic(), s.frame, s.generation)
            pos = (start[1] + int((time.monotonic() - start[0]) * s.fps)) % len(s.labels)
            if pos != s.frame:
                self.set_frame(pos)
            self._poll_video()
        self._poll_video()

    def _poll_video(self) -> None:
        job = self._video_job
        if job is None or time.monotonic() - self._video_polled < 0.25:  # a child process: 4 looks a second
            return
        self._video_polled = time.monotonic()
        outcome = job.poll()
        if outcome is None:
            progress = f"saving video: {job.progress()}"
            if progress != self._extra:
                self.set_status(progress)
            return
        self._video_job = None
        self._update(can_video=self.video_fn is not None, extra=outcome)

    def stop(self) -> None:
        self._stop.set()
        self._want_pose()
        if self._video_job is not None:
            self._video_job.cancel()
        for th in self._threads:
            th.join(2.0)
