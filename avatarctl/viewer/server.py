"""The viser page of the viewer (the `view` extra), for ray-marched avatars: progressive server renders.

A thin front-end over `viewer.controller.ViewerController` (the panel's state, play, render, save video): its widgets
call the controller's setters and follow its `ViewState`. What it adds: the images. While the camera moves (or a
slider changes) each tab gets a low-resolution render, a full one once still (`ProgressiveRenderer`), and, when the
session has a mesh callback, the frame's posed mesh drawn by the page over the previews while the full render
refines (hidden when the full image arrives). Gaussian-field avatars are served by our own page instead
(`viewer.splat_server.SplatPageServer`: the browser draws their splats).

The GUI panel (shared by all tabs): motion (the project's frames, the `--poses` files, any motion file typed in),
frame slider, play / pause at the motion's frame rate, latent mode, resolution of the server render, the video
camera path and "save video", and a status line.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Any

import numpy as np

from avatarctl.viewer.controller import CAMERA_PATHS, LATENTS, ViewerController, ViewState
from avatarctl.viewer.progressive import ProgressiveRenderer, ViewRequest
from avatarctl.viewer.session import ViewerSession


@dataclass(frozen=True)
class InitialView:
    """Where a new tab's camera starts (world, metres)."""

    position: tuple[float, float, float]
    look_at: tuple[float, float, float]
    up: tuple[float, float, float]
    fov_y: float | None = None  # vertical field of view, radians; None = the page's default


def import_viser() -> Any:
    try:
        import viser
    except ImportError:
        raise ImportError("the viewer needs viser: pip install 'avatarctl[view]'") from None
    return viser


def page_url(host: str, port: int) -> str:
    """The address to print for a server listening on (host, port): localhost for the loopback / any address."""
    return f"http://{'localhost' if host in ('0.0.0.0', '127.0.0.1', '::', '') else host}:{port}"


class ViewerServer:
    """A running viser page over `controller` (ray-marched avatars); `url` to open, `stop()` to end it (also stops
    every thread it started, and the controller)."""

    def __init__(self, controller: ViewerController, initial: InitialView, host: str = "127.0.0.1",
                 port: int = 8080, preview_scale: float = 0.25, settle_s: float = 0.3):
        viser = import_viser()
        if controller.session.gaussian:
            raise ValueError("a Gaussian-field avatar is served by viewer.splat_server.SplatPageServer")
        self.controller, self.session, self.initial = controller, controller.session, initial
        self._renderers: dict[int, ProgressiveRenderer] = {}
        self._clients: dict[int, Any] = {}
        self._mesh_handles: dict[int, Any] = {}
        self.preview_scale, self.settle_s = preview_scale, settle_s
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        gui = self.server.gui
        gui.configure_theme(control_width="small", show_share_button=False)
        gui.main_panel.dock_right()  # the canvas keeps the rest of the page
        s = controller.state
        self.motion = gui.add_dropdown("motion", options=s.motions, initial_value=s.motion,
                                       disabled=len(s.motions) < 2)
        self.motion_file = gui.add_text("motion file", initial_value="", disabled=not s.can_load,
                                        hint="a motion file on this machine (AMASS / anny npz, AIST++ pkl, BVH)")
        self.load = gui.add_button("load motion", disabled=not s.can_load)
        n = len(s.labels)
        self.frame = gui.add_slider("frame", min=0, max=max(n - 1, 1), step=1, initial_value=0, disabled=n < 2)
        self.play = gui.add_checkbox("play", initial_value=False)
        self.fps = gui.add_number("fps", initial_value=s.fps, min=0.5, max=240.0, step=0.5)
        self.latent = gui.add_dropdown("latent", options=LATENTS, initial_value=s.latent)
        self.resolution = gui.add_slider("resolution", min=64, max=1024, step=32, initial_value=s.resolution)
        self.camera_path = gui.add_dropdown("video camera", options=CAMERA_PATHS, initial_value=s.camera_path)
        self.save_video = gui.add_button("save video", disabled=not s.can_video,
                                         hint="run `avatarctl render` for this motion, latent and camera path")
        self.status = gui.add_markdown(self._markdown(s))
        c = controller
        self.frame.on_update(lambda _: c.set_frame(int(self.frame.value)))
        self.play.on_update(lambda _: c.set_playing(bool(self.play.value)))
        self.fps.on_update(lambda _: c.set_fps(float(self.fps.value)))
        self.latent.on_update(lambda _: c.set_latent(str(self.latent.value)))
        self.resolution.on_update(lambda _: c.set_resolution(int(self.resolution.value)))
        self.camera_path.on_update(lambda _: c.set_camera_path(str(self.camera_path.value)))
        self.motion.on_update(lambda _: c.switch_motion(str(self.motion.value)))
        self.load.on_click(lambda _: c.switch_motion(str(self.motion_file.value), add=True))
        self.save_video.on_click(lambda _: c.start_video())
        self._shown = s
        self._unsubscribe = controller.subscribe(self._follow)
        self.server.on_client_connect(self._connect)
        self.server.on_client_disconnect(self._disconnect)

    @property
    def url(self) -> str:
        return page_url(self.server.get_host(), self.server.get_port())

    # ---- the panel follows the controller ----------------------------------------------------------------------
    @staticmethod
    def _markdown(s: ViewState) -> str:
        first, *rest = s.status.split("\n")
        return f"**{first}**" + "".join(f"  \n{line}" for line in rest)

    def _follow(self, s: ViewState) -> None:
        old, self._shown = self._shown, s
        if s.motions != old.motions:
            self.motion.options = s.motions
        self.motion.value = s.motion
        n = len(s.labels)
        self.frame.max, self.frame.disabled = max(n - 1, 1), n < 2
        self.frame.value = s.frame
        self.play.value, self.fps.value, self.latent.value = s.playing, s.fps, s.latent
        self.resolution.value, self.camera_path.value = s.resolution, s.camera_path
        self.save_video.disabled = not s.can_video
        self.status.content = self._markdown(s)
        if (s.key, s.resolution) != (old.key, old.resolution):
            self._refresh_all()

    # ---- tabs --------------------------------------------------------------------------------------------------
    def _request(self, client: Any, resolution: int | None = None) -> ViewRequest:
        cam = client.camera
        return self.controller.request(cam.wxyz, cam.position, cam.fov, cam.aspect, resolution)

    def _connect(self, client: Any) -> None:
        client.camera.up_direction = self.initial.up
        client.camera.position = self.initial.position
        client.camera.look_at = self.initial.look_at
        if self.initial.fov_y is not None:
            client.camera.fov = self.initial.fov_y
        self._clients[client.client_id] = client

        def show(image: np.ndarray, req: ViewRequest, full: bool) -> None:
            client.scene.set_background_image(image, format="jpeg", jpeg_quality=90)
            mesh = self._mesh_handles.get(client.client_id)
            if mesh is not None:
                mesh.visible = not full
            quality = "full" if full else "preview"
            self.controller.set_status(f"{image.shape[1]}x{image.shape[0]} {quality} · "
                                       f"{self.session.last_seconds * 1000:.0f} ms")

        def error(e: BaseException) -> None:
            self.controller.set_status(f"render failed: {type(e).__name__}: {e}")

        renderer = ProgressiveRenderer(self.session.render, show, self.preview_scale, self.settle_s, on_error=error)
        self._renderers[client.client_id] = renderer
        client.camera.on_update(lambda _: self._refresh(client.client_id))
        if self.session.mesh_fn is not None:
            threading.Thread(target=self._send_mesh, args=(client,), daemon=True).start()

    def _disconnect(self, client: Any) -> None:
        renderer = self._renderers.pop(client.client_id, None)
        for table in (self._clients, self._mesh_handles):
            table.pop(client.client_id, None)
        if renderer is not None:
            renderer.stop(timeout=0.5)

    # ---- progressive renders and a mesh preview ----------------------------------------------------------------
    def _send_mesh(self, client: Any) -> None:
        key = self.controller.state.key
        try:
            mesh = self.session.mesh(key.frame, key.latent)
        except Exception as e:  # noqa: BLE001 - the preview is optional; the renders go on
            self.controller.set_status(f"mesh preview failed: {type(e).__name__}: {e}")
            return
        if mesh is None or client.client_id not in self._clients or key != self.controller.state.key:
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

    def stop(self) -> None:
        self._unsubscribe()
        self.controller.stop()
        for renderer in list(self._renderers.values()):
            renderer.stop(timeout=2.0)
        self._renderers.clear()
        self.server.stop()
