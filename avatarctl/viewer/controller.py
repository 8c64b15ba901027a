"""What the viewer's controls do, once for every page: the state of the panel, play, posing, render, save video.

Two front-ends sit on one `ViewerController`: the viser page (`viewer.server.ViewerServer`, ray-marched avatars:
progressive server renders) and our own page (`viewer.splat_server.SplatPageServer`, Gaussian-field avatars: the
browser draws each frame's posed Gaussians). A front-end turns its widgets into the controller's setters
(`set_frame`, `set_playing`, `switch_motion`, ...) and shows what the controller reports:
- `subscribe(on_state)`: called with a `ViewState` after every change (frame, motion, status line, ...);
- `subscribe_frames(on_frame)` (Gaussian-field avatars): called with each frame to show, in its wire form
  (`viewer.splats.EncodedSplats`), from the posing thread or, for a frame found in the cache, from the thread that
  changed the frame (the play clock, a setter). One posing thread poses the newest (motion, frame, latent) asked
  for: a frame asked for while another is being posed replaces the one waiting (dropped, never queued). Callbacks
  must not block.

Posing ahead (Gaussian-field avatars): every frame is made by one path, `frame_data(key)`: the session's posed
Gaussians (`ViewerSession.splats`), encoded once (`splats.encode_splats`), kept in a bounded LRU `FrameCache` of
encoded frames (`cache_frames` frames and `cache_bytes` bytes at most; emptied when the latent mode or the motion
changes), so scrubbing back over recent frames, or a motion looping within the cache, costs no posing. While the
motion plays, the posing thread, once the frame asked for is done, poses the frames the play clock will reach next:
the first not yet cached of `ahead` consecutive frames that start at the first frame a posing started now can
finish before the clock gets there (the clock's frame + the frames it passes during one posing: the measured cost
of a frame times the fps, plus 10 %, at least 1). When posing is slower than the clock, the frames it would show
late are skipped and the thread stays busy on frames it finishes in time. A frame the clock reaches is shown from
the cache at once (even while the posing thread poses another); a clock frame not in the cache is not posed (it
would be shown late) while a look-ahead frame is due; a look-ahead frame finished after the clock passed it is
shown if nothing nearer was. A frame asked for explicitly (`set_frame`, `set_latent`, any change while paused) is
posed before any look-ahead work (newest wins; a look-ahead frame already being posed is finished first).

Play keeps wall-clock time at the motion's frame rate: when posing or drawing is slower, frames are skipped, never
slowed. "save video" starts the `VideoFn` the stage gives (`avatarctl render` in a child process) and reports its
progress in the status line. Thread-safe; callbacks run outside the controller's lock.
"""

from __future__ import annotations

import math
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Callable, Protocol

import numpy as np

from avatarctl.viewer.progressive import ViewRequest
from avatarctl.viewer.splats import EncodedSplats

if TYPE_CHECKING:
    from avatarctl.viewer.session import ViewerSession

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


class FrameCache:
    """A bounded LRU of encoded frames keyed by `FrameKey` (at most `max_frames` frames and `max_bytes` bytes of
    payload; the newest is kept even alone over `max_bytes`). Thread-safe. `clear()` starts a new epoch: a frame
    posed before it (`put` with the older `epoch`) is not stored."""

    def __init__(self, max_frames: int = 512, max_bytes: int = 384 * 2 ** 20):
        if max_frames < 1:
            raise ValueError(f"a frame cache holds at least one frame, not {max_frames}")
        self.max_frames, self.max_bytes = int(max_frames), int(max_bytes)
        self._frames: OrderedDict[FrameKey, EncodedSplats] = OrderedDict()
        self._lock = threading.Lock()
        self._bytes = 0
        self.epoch = 0

    def __len__(self) -> int:
        return len(self._frames)

    def __contains__(self, key: FrameKey) -> bool:
        return key in self._frames

    @property
    def nbytes(self) -> int:
        return self._bytes

    def keys(self) -> list[FrameKey]:
        """Oldest used first."""
        with self._lock:
            return list(self._frames)

    def get(self, key: FrameKey) -> EncodedSplats | None:
        with self._lock:
            data = self._frames.get(key)
            if data is not None:
                self._frames.move_to_end(key)
            return data

    def put(self, key: FrameKey, data: EncodedSplats, epoch: int | None = None) -> None:
        with self._lock:
            if epoch is not None and epoch != self.epoch:
                return
            old = self._frames.pop(key, None)
            self._bytes -= old.nbytes if old is not None else 0
            self._frames[key] = data
            self._bytes += data.nbytes
            while len(self._frames) > 1 and (len(self._frames) > self.max_frames or self._bytes > self.max_bytes):
                self._bytes -= self._frames.popitem(last=False)[1].nbytes

    def clear(self) -> None:
        with self._lock:
            self._frames.clear()
            self._bytes = 0
            self.epoch += 1


class ViewerController:
    """The state of the viewer's controls and the work behind them (module docstring); `stop()` ends its threads."""

    def __init__(self, session: "ViewerSession", fps: float | None = None, latent: str = "auto",
                 resolution: int = 512, motions: tuple[str, ...] = (), video: VideoFn | None = None,
                 ahead: int = 3, cache_frames: int = 512, cache_bytes: int = 384 * 2 ** 20):
        if latent not in LATENTS:
            raise ValueError(f"latent {latent!r} not one of {LATENTS}")
        self.ahead = max(int(ahead), 0)  # frames posed ahead of the play clock (module docstring)
        self.cache = FrameCache(cache_frames, cache_bytes)
        self.pose_seconds = 0.05  # running mean of posing + encoding one uncached frame (sets the look-ahead stride)
        self._asked: FrameKey | None = None  # the newest key asked for explicitly (posed before any look-ahead)
        self._failed: set[FrameKey] = set()  # look-ahead frames whose posing failed (not tried again)
        self._delivered: FrameKey | None = None  # the frame handed to the frame subscribers last
        self._deliver_lock = threading.Lock()
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
        self._frame_cbs: list[Callable[[FrameKey, EncodedSplats], None]] = []
        self._stop = threading.Event()
        self._wake = threading.Condition()
        self._video_job: VideoJob | None = None
        self._video_polled = 0.0
        self.posed: list[tuple[float, FrameKey]] = []  # (monotonic time, key) of every frame posed and encoded
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

    def subscribe_frames(self, on_frame: Callable[[FrameKey, EncodedSplats], None]) -> Callable[[], None]:
        """Call `on_frame(key, encoded)` for each frame to show (Gaussian fields); asks for the current one."""
        with self._lock:
            self._frame_cbs.append(on_frame)
        self._want_pose()
        return lambda: self._remove(self._frame_cbs, on_frame)

    def _remove(self, table: list, cb: Callable) -> None:
        with self._lock:
            if cb in table:
                table.remove(cb)

    def latest_frame(self) -> tuple[FrameKey, EncodedSplats]:
        """The current frame, encoded, posed now if not cached (Gaussian fields)."""
        key = self._state.key
        return key, self.frame_data(key)

    def frame_data(self, key: FrameKey) -> EncodedSplats:
        """The encoded frame of `key` from the cache, else posed (`session.splats`) and encoded now, and cached: the
        one path by which the viewer makes a frame (the posing thread, its look-ahead, a new tab's first frame)."""
        data = self.cache.get(key)
        if data is not None:
            return data
        epoch = self.cache.epoch
        t0 = time.perf_counter()
        data = EncodedSplats.of(self.session.splats(key.frame, key.latent))
        self.pose_seconds += 0.3 * (time.perf_counter() - t0 - self.pose_seconds)
        self.cache.put(key, data, epoch)
        self.posed.append((time.monotonic(), key))
        del self.posed[:-1000]
        return data

    # ---- changing the state ------------------------------------------------------------------------------------
    def _status_text(self, s: ViewState, extra: str = "") -> str:
        label = s.labels[min(s.frame, len(s.labels) - 1)]
        mode = "splats drawn by the page" if s.gaussian else "server render"
        note = f" · {self.session.motion.note}" if self.session.motion.note else ""
        return f"{label} · {mode}{note}" + (f"\n{extra}" if extra else "")

    def _update(self, extra: str | None = None, asked: bool = False, **changes) -> ViewState:
        """Apply `changes` (and a new status detail when `extra` is given), tell the subscribers if anything
        changed; returns the new state. `asked`: the new frame is asked for explicitly (posed before look-ahead).
        A new latent mode or motion empties the frame cache."""
        with self._lock:
            old = self._state
            if extra is not None:
                self._extra = extra
            new = replace(old, **changes)
            new = replace(new, status=self._status_text(new, self._extra))
            if new == old:
                return old
            if (new.generation, new.latent) != (old.generation, old.latent):
                self.cache.clear()
                self._failed.clear()
            if asked:
                self._asked = new.key
            self._state = new
            cbs = list(self._state_cbs)
        if new.key != old.key and new.gaussian:
            data = self.cache.get(new.key) if self._frame_cbs else None
            if data is not None:
                self._deliver(new.key, data)
            self._want_pose()  # the frame to pose, or the look-ahead, moved
        for cb in cbs:
            cb(new)
        return new

    def set_status(self, extra: str) -> None:
        """The second line of the status (render time, errors, video progress)."""
        self._update(extra=extra)

    def set_frame(self, frame: int) -> None:
        n = len(self._state.labels)
        self._update(frame=int(min(max(int(frame), 0), n - 1)), asked=True)

    def set_latent(self, latent: str) -> None:
        if latent not in LATENTS:
            self.set_status(f"unknown latent mode {latent!r} (one of {', '.join(LATENTS)})")
            return
        self._update(latent=latent, asked=True)

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

    def ahead_keys(self, s: ViewState | None = None) -> list[FrameKey]:
        """The frames the play clock will reach next (module docstring): `ahead` consecutive frames from the first one
        a posing started now can finish before the clock gets there; none while paused."""
        s = self._state if s is None else s
        n = len(s.labels)
        if not (s.playing and n > 1 and self.ahead):
            return []
        first = s.frame + self._stride(s)
        frames = dict.fromkeys((first + j) % n for j in range(self.ahead))
        return [FrameKey(s.generation, f, s.latent) for f in frames if f != s.frame]

    def _stride(self, s: ViewState) -> int:
        """Frames the clock passes during one posing (10 % margin), at least 1."""
        return max(1, math.ceil(self.pose_seconds * s.fps * 1.1))

    def _next_job(self) -> tuple[bool, FrameKey] | None:
        """(to show, key) of the posing thread's next work, None when there is none: the frame shown first when it
        is asked for or paused; else the first look-ahead frame not cached (those cached are marked used: the cache
        drops frames played before frames still ahead); else the frame shown."""
        s, delivered = self._state, self._delivered
        key = s.key
        if key != delivered and (key == self._asked or not s.playing):
            return True, key
        for k in self.ahead_keys(s):
            if self.cache.get(k) is None and k not in self._failed:
                return False, k
        return (True, key) if key != delivered else None

    def _deliver(self, key: FrameKey, data: EncodedSplats, window: int | None = None) -> bool:
        """Hand a frame to the frame subscribers if it is the frame shown now, or one the clock has passed by at most
        `window` frames (None: half the motion) nearer to the clock than the frame delivered last (newest wins:
        never an older picture after a newer one); True if it was handed."""
        with self._deliver_lock:
            s, delivered = self._state, self._delivered
            if key.generation != s.generation or key.latent != s.latent or key == delivered:
                return False
            if key != s.key:
                n = len(s.labels)
                behind = (s.frame - key.frame) % n
                if not 0 < behind <= min(n // 2, n if window is None else window):
                    return False
                if delivered is not None and (delivered.generation, delivered.latent) == (key.generation, key.latent) \
                        and (s.frame - delivered.frame) % n <= behind:
                    return False
            self._delivered = key
            with self._lock:
                cbs = list(self._frame_cbs)
            for cb in cbs:
                cb(key, data)
            return True

    def _pose_loop(self) -> None:
        """Pose the newest frame asked for and hand it to the frame subscribers (newest wins); pose ahead while
        playing (module docstring). A frame the clock reaches in the cache is handed by the clock (`_update`)."""
        while True:
            with self._wake:
                job = None
                while not self._stop.is_set() and (not self._frame_cbs or (job := self._next_job()) is None):
                    self._wake.wait(0.5)
                if self._stop.is_set():
                    return
            show, key = job
            try:
                data = self.frame_data(key)
            except Exception as e:  # noqa: BLE001 - reported in the page; the viewer keeps serving
                self.set_status(f"posing failed: {type(e).__name__}: {e}")
                if show:
                    with self._deliver_lock:
                        self._delivered = key  # not tried again until another frame is asked for
                else:
                    self._failed.add(key)
                continue
            self._deliver(key, data, None if show else self._stride(self._state) + self.ahead)

    def _play_loop(self) -> None:
        """While playing, the frame follows wall-clock time at the fps (frames skipped when drawing is slow); a frame
        set meanwhile (the slider) restarts the clock from it."""
        start: tuple[float, int, int] | None = None  # (time, frame, motion generation) when play started
        last = -1  # the frame the clock set last
        while not self._stop.wait(0.005 if start else 0.05):
            s = self._state
            if not (s.playing and len(s.labels) > 1):
                start = None
                self._poll_video()
                continue
            if start is None or start[2] != s.generation or s.frame != last:
                start, last = (time.monotonic(), s.frame, s.generation), s.frame
            pos = (start[1] + int((time.monotonic() - start[0]) * s.fps)) % len(s.labels)
            if pos != s.frame:
                last = pos
                self._update(frame=pos)
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
