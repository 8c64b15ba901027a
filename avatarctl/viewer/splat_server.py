"""Our own page for Gaussian-field avatars: an HTTP + websocket server (the `websockets` package, the `view` extra)
in the viewer process, a thin front-end over `viewer.controller.ViewerController`.

- `GET /` is the page (`viewer.splat_page`: the shared WebGL2 splat renderer of `splat.webgl` and the panel);
- `/ws` is one websocket per tab: the panel's state as JSON text after every change, each newly posed frame as
  binary (`splats.encode_splats`, 22 bytes a Gaussian), the PNG of a server render when asked; the page's controls
  come back as JSON commands (`splat_page` lists them).

Flow: the controller encodes each posed frame once (`ViewerController.frame_data`, cached there and posed ahead
while playing); the server packs it with a sequence number per frame shown; every tab has one sender thread holding
only the newest state, the newest frame and the newest image. A frame is sent when the tab has drawn the previous one
(its "drawn" answer, or after `ACK_TIMEOUT_S`): a slow tab skips frames, it never gets a queue of them.
"""

from __future__ import annotations

import json
import logging
import struct
import threading
import time
from dataclasses import asdict
from typing import TYPE_CHECKING, Any

import numpy as np

from avatarctl.viewer.controller import FrameKey, ViewerController, ViewState
from avatarctl.viewer.server import InitialView, page_url
from avatarctl.viewer.session import matrix_to_quaternion_wxyz
from avatarctl.viewer.splat_page import page_html

if TYPE_CHECKING:
    from avatarctl.viewer.splats import EncodedSplats

ACK_TIMEOUT_S = 2.0  # a tab that has not said "drawn" by then gets the next frame anyway


def import_websockets() -> Any:
    try:
        import websockets.sync.server as server
    except ImportError:
        raise ImportError("the viewer needs websockets: pip install 'avatarctl[view]'") from None
    return server


def pack(header: dict, payload: bytes) -> bytes:
    """uint32 n + the n-byte JSON header (padded so the payload starts at a multiple of 4) + payload."""
    text = json.dumps(header).encode()
    text += b" " * (-(4 + len(text)) % 4)
    return struct.pack("<I", len(text)) + text + payload


class _Tab:
    """One open page: its connection and the newest things to send it (one sender thread)."""

    def __init__(self, connection: Any):
        self.connection = connection
        self.wake = threading.Condition()
        self.state: str | None = None
        self.frame: tuple[int, bytes] | None = None  # (seq, message)
        self.image: bytes | None = None
        self.sent_seq, self.acked_seq, self.sent_at = -1, -1, 0.0
        self.closed = False

    def offer(self, state: str | None = None, frame: tuple[int, bytes] | None = None,
              image: bytes | None = None) -> None:
        with self.wake:
            if state is not None:
                self.state = state
            if frame is not None:
                self.frame = frame
            if image is not None:
                self.image = image
            self.wake.notify_all()

    def ack(self, seq: int) -> None:
        with self.wake:
            self.acked_seq = max(self.acked_seq, seq)
            self.wake.notify_all()

    def close(self) -> None:
        with self.wake:
            self.closed = True
            self.wake.notify_all()

    def _frame_due(self) -> bool:
        return self.frame is not None and self.frame[0] != self.sent_seq and (
            self.acked_seq >= self.sent_seq or time.monotonic() - self.sent_at > ACK_TIMEOUT_S)

    def send_loop(self, sent: list[tuple[float, int]]) -> None:
        while True:
            with self.wake:
                while not self.closed and self.state is None and self.image is None and not self._frame_due():
                    self.wake.wait(0.25)
                if self.closed:
                    return
                state, image, self.state, self.image = self.state, self.image, None, None
                frame = self.frame if self._frame_due() else None
                if frame is not None:
                    self.sent_seq, self.sent_at = frame[0], time.monotonic()
            try:
                for message in (state, image, frame[1] if frame else None):
                    if message is not None:
                        self.connection.send(message)
            except Exception:  # noqa: BLE001 - the tab closed meanwhile
                self.close()
                return
            if frame is not None:
                sent.append((time.monotonic(), frame[0]))
                del sent[:-1000]


class SplatPageServer:
    """A running page for a Gaussian-field avatar over `controller`; `url` to open, `stop()` to end it (its threads,
    the open tabs and the controller)."""

    def __init__(self, controller: ViewerController, initial: InitialView, host: str = "127.0.0.1",
                 port: int = 8080):
        ws_server = import_websockets()
        session = controller.session
        if not session.gaussian:
            raise ValueError("a ray-marched avatar is served by viewer.server.ViewerServer")
        fov = initial.fov_y if initial.fov_y is not None else 0.8
        self.controller, self.session, self.host = controller, session, host
        self.page = page_html(session.background, initial.position, initial.look_at, initial.up, fov,
                              session.model.cfg.gaussians.low_pass).encode()
        self.pushes: list[tuple[float, int]] = []  # (monotonic time, seq) of every frame sent to a tab
        self._tabs: dict[int, _Tab] = {}
        self._lock = threading.Lock()
        self._seq = 0
        self._last: tuple[FrameKey, int, bytes] | None = None  # the newest encoded frame
        quiet = logging.getLogger("avatarctl.viewer.websocket")  # browsers open idle speculative connections: their
        quiet.setLevel(logging.CRITICAL)  # failed handshakes are no error of the viewer
        self._server = ws_server.serve(self._handle, host, port, process_request=self._http, compression=None,
                                       max_size=2 ** 20, logger=quiet)
        self.port = int(self._server.socket.getsockname()[1])
        self._unsubscribe = (controller.subscribe(self._on_state), controller.subscribe_frames(self._on_frame))
        self._thread = threading.Thread(target=self._server.serve_forever, name="avatarctl-viewer-http",
                                        daemon=True)
        self._thread.start()

    @property
    def url(self) -> str:
        return page_url(self.host, self.port)

    # ---- HTTP and the websocket --------------------------------------------------------------------------------
    def _http(self, connection: Any, request: Any) -> Any:
        path = request.path.split("?")[0]
        if path == "/ws":
            return None  # the websocket handshake goes on
        if path not in ("/", "/index.html"):
            return connection.respond(404, f"no {path} here: open /\n")
        response = connection.respond(200, "")
        response.body = self.page
        del response.headers["Content-Type"], response.headers["Content-Length"]
        response.headers["Content-Type"] = "text/html; charset=utf-8"
        response.headers["Content-Length"] = str(len(self.page))
        response.headers["Cache-Control"] = "no-store"
        return response

    def _handle(self, connection: Any) -> None:
        tab = _Tab(connection)
        with self._lock:
            self._tabs[id(tab)] = tab
        sender = threading.Thread(target=tab.send_loop, args=(self.pushes,), name="avatarctl-viewer-send",
                                  daemon=True)
        sender.start()
        tab.offer(state=self._state_json(self.controller.state))
        try:
            tab.offer(frame=self._current())
            for message in connection:
                if isinstance(message, str):
                    self._command(tab, json.loads(message))
        except Exception as e:  # noqa: BLE001 - a closed tab, a bad message: the viewer keeps serving
            if type(e).__name__ not in ("ConnectionClosedOK", "ConnectionClosedError", "ConnectionClosed"):
                self.controller.set_status(f"page error: {type(e).__name__}: {e}")
        finally:
            tab.close()
            with self._lock:
                self._tabs.pop(id(tab), None)
            sender.join(2.0)

    def _command(self, tab: _Tab, msg: dict) -> None:
        c, cmd, value = self.controller, msg.get("cmd"), msg.get("value")
        if cmd == "drawn":
            tab.ack(int(msg["seq"]))
        elif cmd == "frame":
            c.set_frame(int(value))
        elif cmd == "play":
            c.set_playing(bool(value))
        elif cmd == "fps":
            c.set_fps(float(value))
        elif cmd == "latent":
            c.set_latent(str(value))
        elif cmd == "resolution":
            c.set_resolution(int(value))
        elif cmd == "camera_path":
            c.set_camera_path(str(value))
        elif cmd == "video":
            c.start_video()
        elif cmd == "motion":
            threading.Thread(target=c.switch_motion, args=(str(msg.get("name", "")), bool(msg.get("add"))),
                             daemon=True).start()
        elif cmd == "render":
            threading.Thread(target=self._render, args=(tab, msg["view"], float(msg["aspect"])), daemon=True).start()
        else:
            c.set_status(f"the page sent an unknown command {cmd!r}")

    def _render(self, tab: _Tab, view: dict, aspect: float) -> None:
        """The exact image of the tab's camera (`view`: eye, right, down, fwd, fov; OpenCV axes) as a PNG."""
        import cv2

        R_wc = np.stack([np.asarray(view[k], np.float64) for k in ("right", "down", "fwd")], axis=1)
        req = self.controller.request(matrix_to_quaternion_wxyz(R_wc), tuple(view["eye"]), float(view["fov"]),
                                      aspect)
        key = self.controller.state.key  # the frame of the image: the page keeps it up while it draws this frame
        try:
            image = self.controller.render(req)
        except Exception:  # noqa: BLE001 - the status line says why
            tab.offer(image=pack({"kind": "error"}, b""))
            return
        ok, png = cv2.imencode(".png", np.ascontiguousarray(image[..., ::-1]))
        tab.offer(image=pack({"kind": "image", "width": int(image.shape[1]), "height": int(image.shape[0]),
                              "generation": key.generation, "frame": req.frame, "latent": req.latent}, png.tobytes()))

    # ---- what the controller reports ---------------------------------------------------------------------------
    @staticmethod
    def _state_json(s: ViewState) -> str:
        return json.dumps(asdict(s))

    def _on_state(self, s: ViewState) -> None:
        text = self._state_json(s)
        with self._lock:
            tabs = list(self._tabs.values())
        for tab in tabs:
            tab.offer(state=text)

    def _message(self, key: FrameKey, data: "EncodedSplats") -> tuple[int, bytes]:
        """(seq, the binary message) of a frame to show; a new seq unless it is the newest message's frame."""
        with self._lock:
            if self._last is not None and self._last[0] == key:
                return self._last[1], self._last[2]
            self._seq += 1
            seq = self._seq
        message = pack({"kind": "splats", "seq": seq, "generation": key.generation, "frame": key.frame,
                        "latent": key.latent, **data.header}, data.payload)
        with self._lock:
            self._last = (key, seq, message)
        return seq, message

    def _on_frame(self, key: FrameKey, data: "EncodedSplats") -> None:
        frame = self._message(key, data)
        with self._lock:
            tabs = list(self._tabs.values())
        for tab in tabs:
            tab.offer(frame=frame)

    def _current(self) -> tuple[int, bytes]:
        """The frame shown now, for a new tab (posed now if the posing thread has not yet)."""
        key, data = self.controller.latest_frame()
        return self._message(key, data)

    def stop(self) -> None:
        for unsubscribe in self._unsubscribe:
            unsubscribe()
        self.controller.stop()
        with self._lock:
            tabs = list(self._tabs.values())
        for tab in tabs:
            tab.close()
            try:
                tab.connection.close()
            except Exception:  # noqa: BLE001 - already closed
                pass
        self._server.shutdown()
        self._thread.join(2.0)
