"""The web viewer: a viser server (the `view` extra) showing a `ViewerSession`'s renders as the page background.

Per browser tab: the orbit camera of the page drives a `ProgressiveRenderer` (low resolution while it moves, full
once still); the GUI panel holds the frame slider (training and test frames, or a motion file's), play / pause,
the latent mode (auto / mean / zero / sample), the resolution, and a status line (frame, resolution, render time).
Renders of all tabs are serialised by one lock (one model, one device).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Any

import numpy as np

from avatarctl.viewer.progressive import ProgressiveRenderer, ViewRequest
from avatarctl.viewer.session import ViewerSession

LATENTS = ("auto", "mean", "zero", "sample")


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


class ViewerServer:
    """A running viewer; `url` to open, `stop()` to end it (also stops every render thread)."""

    def __init__(self, session: ViewerSession, initial: InitialView, host: str = "127.0.0.1", port: int = 8080,
                 resolution: int = 512, preview_scale: float = 0.25, settle_s: float = 0.3, fps: float = 10.0,
                 latent: str = "auto"):
        viser = import_viser()
        self.session, self.initial = session, initial
        self._lock = threading.Lock()
        self._renderers: dict[int, ProgressiveRenderer] = {}
        self._clients: dict[int, Any] = {}
        self._stop_play = threading.Event()
        self.preview_scale, self.settle_s, self.fps = preview_scale, settle_s, max(float(fps), 0.1)
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        gui = self.server.gui
        n = len(session.frames)
        self.frame = gui.add_slider("frame", min=0, max=max(n - 1, 1), step=1, initial_value=0, disabled=n < 2)
        self.play = gui.add_checkbox("play", initial_value=False)
        self.latent = gui.add_dropdown("latent", options=LATENTS, initial_value=latent)
        self.resolution = gui.add_slider("resolution", min=64, max=1024, step=32, initial_value=int(resolution))
        self.status = gui.add_markdown(self._status_text(None))
        for handle in (self.frame, self.latent, self.resolution):
            handle.on_update(lambda _: self._refresh_all())
        self.server.on_client_connect(self._connect)
        self.server.on_client_disconnect(self._disconnect)
        self._player = threading.Thread(target=self._play_loop, name="avatarctl-viewer-play", daemon=True)
        self._player.start()

    @property
    def url(self) -> str:
        host = self.server.get_host()
        return f"http://{'localhost' if host in ('0.0.0.0', '127.0.0.1') else host}:{self.server.get_port()}"

    def _status_text(self, seconds: float | None, size: tuple[int, int] | None = None, full: bool = True) -> str:
        pos = int(self.frame.value)
        label = self.session.frames[min(pos, len(self.session.frames) - 1)].label
        if seconds is None:
            return f"**{label}**"
        quality = "full" if full else "preview"
        return f"**{label}** · {size[0]}x{size[1]} {quality} · {seconds * 1000:.0f} ms"

    def _request(self, client: Any) -> ViewRequest:
        cam = client.camera
        return ViewRequest(wxyz=tuple(float(c) for c in cam.wxyz), position=tuple(float(c) for c in cam.position),
                           fov_y=float(cam.fov), aspect=float(cam.aspect),
                           frame=min(int(self.frame.value), len(self.session.frames) - 1),
                           latent=str(self.latent.value), resolution=int(self.resolution.value))

    def _connect(self, client: Any) -> None:
        client.camera.up_direction = self.initial.up
        client.camera.position = self.initial.position
        client.camera.look_at = self.initial.look_at
        if self.initial.fov_y is not None:
            client.camera.fov = self.initial.fov_y

        def render(req: ViewRequest, should_stop) -> np.ndarray:
            with self._lock:
                return self.session.render(req, should_stop)

        def show(image: np.ndarray, req: ViewRequest, full: bool) -> None:
            client.scene.set_background_image(image, format="jpeg", jpeg_quality=90)
            self.status.content = self._status_text(self.session.last_seconds, (image.shape[1], image.shape[0]), full)

        def error(e: BaseException) -> None:
            self.status.content = f"render failed: {type(e).__name__}: {e}"

        renderer = ProgressiveRenderer(render, show, self.preview_scale, self.settle_s, on_error=error)
        self._renderers[client.client_id] = renderer
        self._clients[client.client_id] = client
        client.camera.on_update(lambda _: self._refresh(client.client_id))

    def _disconnect(self, client: Any) -> None:
        renderer = self._renderers.pop(client.client_id, None)
        self._clients.pop(client.client_id, None)
        if renderer is not None:
            renderer.stop(timeout=0.5)

    def _refresh(self, client_id: int) -> None:
        renderer, client = self._renderers.get(client_id), self._clients.get(client_id)
        if renderer is None or client is None:
            return
        try:
            renderer.update(self._request(client))
        except AssertionError:  # the tab has not reported its camera yet
            pass

    def _refresh_all(self) -> None:
        for cid in list(self._renderers):
            self._refresh(cid)

    def _play_loop(self) -> None:
        while not self._stop_play.wait(1.0 / self.fps):
            if self.play.value and len(self.session.frames) > 1:
                self.frame.value = (int(self.frame.value) + 1) % len(self.session.frames)
                self._refresh_all()

    def stop(self) -> None:
        self._stop_play.set()
        for renderer in list(self._renderers.values()):
            renderer.stop(timeout=2.0)
        self._renderers.clear()
        self.server.stop()
