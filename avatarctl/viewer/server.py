"""The web viewer: a viser server (the `view` extra) around a `ViewerSession`.

Two ways to draw, chosen by the avatar's field:
- **Gaussian local fields: the browser draws.** Each frame's posed Gaussians (`ViewerSession.splats`, milliseconds)
  are sent to every tab as a viser Gaussian-splat node; the page sorts and draws them itself, so the orbit never
  waits for Python. A frame change sends the new frame's Gaussians (one pusher thread, the newest frame wins: a
  slow push drops frames, never queues them). The **render** button draws the exact image (the renderer of `render`
  and `eval`, view-dependent colour included) of the tab's camera as the page background and hides the splats until
  the camera moves.
- **Ray-marched fields: progressive server renders** as before (low resolution while the view changes, full once
  still; `ProgressiveRenderer`), and, when the session has a mesh callback, the frame's posed mesh drawn by the page
  over the previews while the full render refines (hidden when the full image arrives).

The GUI panel (shared by all tabs): motion (the project's frames, the `--poses` files, any motion file typed in),
frame slider, play / pause at the motion's frame rate (playback keeps wall-clock time: frames are dropped, never
slowed, when pushing is slower), latent mode, resolution of the server render, the render and save-video buttons, and
a status line. "save video" calls the `VideoFn` the stage gives (it runs `avatarctl render` for the current motion,
latent and camera path) and shows its progress.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Any, Callable, Protocol

import numpy as np

from avatarctl.viewer.progressive import ProgressiveRenderer, ViewRequest
from avatarctl.viewer.session import ViewerSession

LATENTS = ("auto", "mean", "zero", "sample")
CAMERA_PATHS = ("held-out view", "orbit")


@dataclass(frozen=True)
class InitialView:
    """Where a new tab's camera starts (world, metres)."""

    position: tuple[float, float, float]
    look_at: tuple[float, float, float]
    up: tuple[float, float, float]
    fov_y: float | None = None  # vertical field of view, radians; None = the page's default


class VideoJob(Protocol):
    """A running "save video": `poll()` is None while it runs, then a one-line outcome; `cancel()` ends it."""

    def poll(self) -> str | None: ...

    def progress(self) -> str: ...

    def cancel(self) -> None: ...


VideoFn = Callable[[str, str, str], VideoJob]  # (motion name, latent mode, camera path) -> a started job


def import_viser() -> Any:
    try:
        import viser
    except ImportError:
        raise ImportError("the viewer needs viser: pip install 'avatarctl[view]'") from None
    return viser


class ViewerServer:
    """A running viewer; `url` to open, `stop()` to end it (also stops every thread it started)."""

    def __init__(self, session: ViewerSession, initial: InitialView, host: str = "127.0.0.1", port: int = 8080,
                 resolution: int = 512, preview_scale: float = 0.25, settle_s: float = 0.3, fps: float | None = None,
                 latent: str = "auto", motions: tuple[str, ...] = (), video: VideoFn | None = None):
        viser = import_viser()
        self.session, self.initial, self.video_fn = session, initial, video
        self._renderers: dict[int, ProgressiveRenderer] = {}
        self._clients: dict[int, Any] = {}
        self._splat_handles: dict[int, Any] = {}
        self._mesh_handles: dict[int, Any] = {}
        self._exact_shown: set[int] = set()
        self._stop = threading.Event()
        self._wake = threading.Condition()
        self._want = 0  # version of the newest (motion, frame, latent) asked for
        self._pushed: dict[int, tuple[int, int, str, int]] = {}  # client -> (motion gen, frame, latent, count) shown
        self._motion_gen = 0
        self._video_job: VideoJob | None = None
        self.pushes: list[tuple[float, int]] = []  # (monotonic time, frame) of every frame pushed to the tabs
        self.preview_scale, self.settle_s = preview_scale, settle_s
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        gui = self.server.gui
        gui.configure_theme(control_width="small", show_share_button=False)
        gui.main_panel.dock_right()  # the canvas keeps the rest of the page
        n = len(session.frames)
        names = tuple(dict.fromkeys((session.motion.name, *motions)))
        self.motion = gui.add_dropdown("motion", options=names, initial_value=session.motion.name,
                                       disabled=len(names) < 2)
        self.motion_file = gui.add_text("motion file", initial_value="", disabled=session.load_motion is None,
                                        hint="a motion file on this machine (AMASS / anny npz, AIST++ pkl, BVH)")
        self.load = gui.add_button("load motion", disabled=session.load_motion is None)
        self.frame = gui.add_slider("frame", min=0, max=max(n - 1, 1), step=1, initial_value=0, disabled=n < 2)
        self.play = gui.add_checkbox("play", initial_value=False)
        self.fps = gui.add_number("fps", initial_value=float(fps or session.motion.fps), min=0.5, max=240.0, step=0.5)
        self.latent = gui.add_dropdown("latent", options=LATENTS, initial_value=latent)
        self.resolution = gui.add_slider("resolution", min=64, max=1024, step=32, initial_value=int(resolution))
        self.render_button = gui.add_button("render", disabled=not session.gaussian,
                                            hint="the exact image of this view (the renderer of `render` / `eval`)")
        self.camera_path = gui.add_dropdown("video camera", options=CAMERA_PATHS, initial_value=CAMERA_PATHS[0])
        self.save_video = gui.add_button("save video", disabled=video is None,
                                         hint="run `avatarctl render` for this motion, latent and camera path")
        self.status = gui.add_markdown(self._status_text())
        self.frame.on_update(lambda _: self._changed())
        self.latent.on_update(lambda _: self._changed())
        self.resolution.on_update(lambda _: self._refresh_all())
        self.motion.on_update(lambda _: self._switch(str(self.motion.value)))
        self.load.on_click(lambda _: self._switch(str(self.motion_file.value).strip(), add=True))
        self.render_button.on_click(lambda event: self._render_exact(event.client))
        self.save_video.on_click(lambda _: self._start_video())
        self.server.on_client_connect(self._connect)
        self.server.on_client_disconnect(self._disconnect)
        self._threads = [threading.Thread(target=self._play_loop, name="avatarctl-viewer-play", daemon=True)]
        if session.gaussian:
            self._threads.append(threading.Thread(target=self._push_loop, name="avatarctl-viewer-push", daemon=True))
        for th in self._threads:
            th.start()

    @property
    def url(self) -> str:
        host = self.server.get_host()
        return f"http://{'localhost' if host in ('0.0.0.0', '127.0.0.1') else host}:{self.server.get_port()}"

    # ---- GUI state ---------------------------------------------------------------------------------------------
    def _position(self) -> int:
        return min(int(self.frame.value), len(self.session.frames) - 1)

    def _status_text(self, extra: str = "") -> str:
        label = self.session.frames[self._position()].label
        mode = "splats drawn by the page" if self.session.gaussian else "server render"
        note = f" · {self.session.motion.note}" if self.session.motion.note else ""
        return f"**{label}** · {mode}{note}" + (f"  \n{extra}" if extra else "")

    def _set_status(self, extra: str = "") -> None:
        self.status.content = self._status_text(extra)

    def _request(self, client: Any, resolution: int | None = None) -> ViewRequest:
        cam = client.camera
        return ViewRequest(wxyz=tuple(float(c) for c in cam.wxyz), position=tuple(float(c) for c in cam.position),
                           fov_y=float(cam.fov), aspect=float(cam.aspect), frame=self._position(),
                           latent=str(self.latent.value), resolution=int(resolution or self.resolution.value))

    def _switch(self, name: str, add: bool = False) -> None:
        """Play another motion (a dropdown entry or a typed file); errors go to the status line."""
        if not name or (name == self.session.motion.name and not add):
            return
        self.play.value = False
        self._set_status(f"loading {name} ...")
        try:
            motion = self.session.set_motion(name)
        except Exception as e:  # noqa: BLE001 - a one-line message in the page; the viewer keeps serving
            self._set_status(f"cannot load {name}: {e}")
            return
        self._motion_gen += 1
        if add and motion.name not in self.motion.options:
            self.motion.options = (*self.motion.options, motion.name)
        self.motion.value = motion.name
        n = len(motion.frames)
        self.frame.max = max(n - 1, 1)
        self.frame.disabled = n < 2
        self.frame.value = 0
        self.fps.value = float(motion.fps)
        self._changed()

    def _changed(self) -> None:
        """The frame, latent or motion changed: new splats for every tab, or new server renders."""
        if self.session.gaussian:
            with self._wake:
                self._want += 1
                self._wake.notify_all()
        else:
            self._refresh_all()
        self._set_status()

    # ---- tabs --------------------------------------------------------------------------------------------------
    def _connect(self, client: Any) -> None:
        client.camera.up_direction = self.initial.up
        client.camera.position = self.initial.position
        client.camera.look_at = self.initial.look_at
        if self.initial.fov_y is not None:
            client.camera.fov = self.initial.fov_y
        self._clients[client.client_id] = client
        if self.session.gaussian:
            client.camera.on_update(lambda _: self._camera_moved(client.client_id))
            with self._wake:
                self._want += 1
                self._wake.notify_all()
            return

        def render(req: ViewRequest, should_stop) -> np.ndarray:
            return self.session.render(req, should_stop)

        def show(image: np.ndarray, req: ViewRequest, full: bool) -> None:
            client.scene.set_background_image(image, format="jpeg", jpeg_quality=90)
            mesh = self._mesh_handles.get(client.client_id)
            if mesh is not None:
                mesh.visible = not full
            quality = "full" if full else "preview"
            self._set_status(f"{image.shape[1]}x{image.shape[0]} {quality} · "
                             f"{self.session.last_seconds * 1000:.0f} ms")

        def error(e: BaseException) -> None:
            self._set_status(f"render failed: {type(e).__name__}: {e}")

        renderer = ProgressiveRenderer(render, show, self.preview_scale, self.settle_s, on_error=error)
        self._renderers[client.client_id] = renderer
        client.camera.on_update(lambda _: self._refresh(client.client_id))
        if self.session.mesh_fn is not None:
            threading.Thread(target=self._send_mesh, args=(client,), daemon=True).start()

    def _disconnect(self, client: Any) -> None:
        renderer = self._renderers.pop(client.client_id, None)
        for table in (self._clients, self._splat_handles, self._mesh_handles, self._pushed):
            table.pop(client.client_id, None)
        self._exact_shown.discard(client.client_id)
        if renderer is not None:
            renderer.stop(timeout=0.5)

    # ---- Gaussian local fields: splats drawn by the page ------------------------------------------------------
    def _push_loop(self) -> None:
        """Send the newest frame's splats to every tab that does not show it yet (one thread, newest wins)."""
        done = -1
        while True:
            with self._wake:
                while not self._stop.is_set() and self._want == done:
                    self._wake.wait(0.5)
                if self._stop.is_set():
                    return
                done = self._want
            pos, latent, gen = self._position(), str(self.latent.value), self._motion_gen
            try:
                splats = self.session.splats(pos, latent)
            except Exception as e:  # noqa: BLE001 - reported in the page; the viewer keeps serving
                self._set_status(f"posing failed: {type(e).__name__}: {e}")
                continue
            key = (gen, pos, latent, splats.count)
            for cid, client in list(self._clients.items()):
                if self._pushed.get(cid) == key:
                    continue
                try:
                    handle = self._splat_handles.get(cid)
                    if handle is None:
                        self._splat_handles[cid] = client.scene.add_gaussian_splats(
                            "/avatar", centers=splats.centers, covariances=splats.covariances, rgbs=splats.rgbs,
                            opacities=splats.opacities, visible=cid not in self._exact_shown)
                    else:
                        handle.set_gaussians(splats.centers, splats.covariances, splats.rgbs, splats.opacities)
                    self._pushed[cid] = key
                except Exception:  # noqa: BLE001 - a tab that closed meanwhile
                    self._pushed.pop(cid, None)
            self.pushes.append((time.monotonic(), pos))
            del self.pushes[:-1000]

    def _camera_moved(self, client_id: int) -> None:
        """The exact image is of one view: the splats come back as soon as the camera moves."""
        if client_id not in self._exact_shown:
            return
        self._exact_shown.discard(client_id)
        client, handle = self._clients.get(client_id), self._splat_handles.get(client_id)
        if client is not None:
            client.scene.set_background_image(None)
        if handle is not None:
            handle.visible = True

    def _render_exact(self, client: Any) -> None:
        if client is None:
            return
        self.render_button.disabled = True
        self._set_status(f"rendering {int(self.resolution.value)} px on the server ...")
        try:
            req = self._request(client)
            image = self.session.render(req)
            client.scene.set_background_image(image, format="png")
            handle = self._splat_handles.get(client.client_id)
            if handle is not None:
                handle.visible = False
            self._exact_shown.add(client.client_id)
            self._set_status(f"exact render {image.shape[1]}x{image.shape[0]} · "
                             f"{self.session.last_seconds * 1000:.0f} ms (move the camera to orbit again)")
        except Exception as e:  # noqa: BLE001 - reported in the page
            self._set_status(f"render failed: {type(e).__name__}: {e}")
        finally:
            self.render_button.disabled = False

    # ---- ray-marched fields: progressive renders and a mesh preview -------------------------------------------
    def _send_mesh(self, client: Any) -> None:
        pos, latent = self._position(), str(self.latent.value)
        try:
            mesh = self.session.mesh(pos, latent)
        except Exception as e:  # noqa: BLE001 - the preview is optional; the renders go on
            self._set_status(f"mesh preview failed: {type(e).__name__}: {e}")
            return
        if mesh is None or client.client_id not in self._clients or (pos, latent) != (self._position(),
                                                                                      str(self.latent.value)):
            return
        vertices, faces = np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.int64)
        colours = np.clip(np.asarray(mesh.colours, np.float32), 0.0, 1.0)  # [verts, 3]
        try:
            import trimesh
        except ImportError:  # one colour: the mean of the vertices'
            handle = client.scene.add_mesh_simple("/mesh_preview", vertices, faces.astype(np.uint32),
                                                  color=tuple(int(c) for c in (colours.mean(0) * 255).round()))
        else:
            rgba = np.concatenate([(colours * 255).round(), np.full((len(colours), 1), 255.0)], 1).astype(np.uint8)
            handle = client.scene.add_mesh_trimesh("/mesh_preview", trimesh.Trimesh(
                vertices, faces, vertex_colors=rgba, process=False))
        self._mesh_handles[client.client_id] = handle

    def _refresh(self, client_id: int) -> None:
        renderer, client = self._renderers.get(client_id), self._clients.get(client_id)
        if renderer is None or client is None:
            return
        mesh = self._mesh_handles.get(client_id)
        if mesh is not None:
            mesh.visible = True
        try:
            renderer.update(self._request(client))
        except AssertionError:  # the tab has not reported its camera yet
            pass

    def _refresh_all(self) -> None:
        for cid in list(self._renderers):
            self._refresh(cid)
            client = self._clients.get(cid)
            if self.session.mesh_fn is not None and client is not None:
                threading.Thread(target=self._send_mesh, args=(client,), daemon=True).start()

    # ---- play and save video -----------------------------------------------------------------------------------
    def _play_loop(self) -> None:
        """While "play" is on, the frame follows wall-clock time at the fps (frames dropped when pushing is slow)."""
        start: tuple[float, int] | None = None
        last_status = 0.0
        while not self._stop.wait(0.005 if start else 0.05):
            n = len(self.session.frames)
            if not (self.play.value and n > 1):
                start = None
                continue
            fps = max(float(self.fps.value), 0.1)
            if start is None:
                start = (time.monotonic(), self._position())
            pos = (start[1] + int((time.monotonic() - start[0]) * fps)) % n
            if pos != self._position():
                self.frame.value = pos
                self._changed()
            if self.session.gaussian and len(self.pushes) > 1 and time.monotonic() - last_status > 0.5:
                last_status = time.monotonic()
                recent = [t for t, _ in self.pushes if t > time.monotonic() - 2.0]
                if len(recent) > 1:
                    self._set_status(f"playing · {(len(recent) - 1) / (recent[-1] - recent[0] + 1e-9):.1f} frames/s "
                                     f"shown (motion {fps:g} fps)")
            self._poll_video()
        self._poll_video()

    def _start_video(self) -> None:
        if self.video_fn is None or self._video_job is not None:
            return
        try:
            self._video_job = self.video_fn(self.session.motion.name, str(self.latent.value),
                                            str(self.camera_path.value))
        except Exception as e:  # noqa: BLE001 - reported in the page
            self._set_status(f"save video failed: {e}")
            return
        self.save_video.disabled = True
        threading.Thread(target=self._watch_video, daemon=True).start()

    def _watch_video(self) -> None:
        while self._video_job is not None and not self._stop.wait(0.5):
            self._poll_video()

    def _poll_video(self) -> None:
        job = self._video_job
        if job is None:
            return
        outcome = job.poll()
        if outcome is None:
            self._set_status(f"saving video: {job.progress()}")
            return
        self._video_job = None
        self.save_video.disabled = False
        self._set_status(outcome)

    def stop(self) -> None:
        self._stop.set()
        with self._wake:
            self._wake.notify_all()
        for renderer in list(self._renderers.values()):
            renderer.stop(timeout=2.0)
        self._renderers.clear()
        if self._video_job is not None:
            self._video_job.cancel()
        for th in self._threads:
            th.join(2.0)
        self.server.stop()
