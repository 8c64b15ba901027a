"""The viewer: camera convention of a request, progressive rendering (preview, full, cancellation), the render
callback on a fitted toy project, and (marked `browser`, skipped without Chromium / viser) the page itself."""

from __future__ import annotations

import json
import threading
import time

import numpy as np
import pytest

from avatarctl.geometry.cameras import Camera, look_at
from avatarctl.viewer.progressive import Cancelled, ProgressiveRenderer, ViewRequest
from avatarctl.viewer.session import request_camera


def _wxyz(R_wc: np.ndarray) -> tuple[float, float, float, float]:
    from avatarctl.export.skinning import matrix_to_quaternion

    x, y, z, w = matrix_to_quaternion(R_wc)
    return (w, x, y, z)


def request_looking_at(eye, target, up=(0, 0, 1.0), resolution=64, aspect=4 / 3, frame=0, latent="auto"):
    R, _ = look_at(np.asarray(eye, float), np.asarray(target, float), np.asarray(up, float))
    return ViewRequest(wxyz=_wxyz(R.T), position=tuple(float(c) for c in eye), fov_y=0.8, aspect=aspect,
                       frame=frame, latent=latent, resolution=resolution)


def test_request_camera_follows_opencv_and_the_fov():
    req = request_looking_at((0, -2.0, 0.5), (0, 0, 0.5), resolution=80)
    cam = request_camera(req)
    assert (cam.width, cam.height) == (80, 60)
    assert np.allclose(cam.center, [0, -2.0, 0.5])
    assert np.allclose(cam.project(np.array([[0, 0, 0.5]])), [[39.5, 29.5]]), "the target at the image centre"
    top = cam.project(np.array([[0, 0, 0.5 + 2.0 * np.tan(0.4)]]))[0]
    assert top[1] == pytest.approx(-0.5, abs=1e-6), "half the vertical fov reaches the top edge; image y down"
    assert request_camera(request_looking_at((0, -2, 0), (0, 0, 0), resolution=80, aspect=0.5)).height == 80


def test_progressive_preview_then_full_and_cancel():
    calls, shown = [], []
    gate = threading.Event()

    def render(req: ViewRequest, should_stop) -> np.ndarray:
        calls.append(req.resolution)
        if req.resolution == 400 and not gate.is_set():  # a slow full render, abandoned by a newer request
            for _ in range(200):
                if should_stop():
                    raise Cancelled()
                time.sleep(0.005)
        return np.zeros((req.resolution, req.resolution, 3), np.uint8)

    pr = ProgressiveRenderer(render, lambda img, req, full: shown.append((img.shape[0], full)), preview_scale=0.25,
                             settle_s=0.1)
    try:
        req = request_looking_at((0, -2, 0), (0, 0, 0), resolution=400)
        pr.update(req)
        time.sleep(0.15)  # the full render starts after 0.1 s of rest ...
        pr.update(req)  # ... and a new request cancels it
        gate.set()
        deadline = time.monotonic() + 5
        while (400, True) not in shown and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        pr.stop()
    assert shown[0] == (100, False), "a preview at a quarter of the resolution first"
    assert shown[-1] == (400, True), "full resolution once still"
    assert calls.count(400) >= 2 and shown.count((400, True)) == 1, "the first full render was abandoned"



def test_a_stream_of_requests_still_shows_previews():
    """Play / a long drag: requests every 10 ms, previews take 40 ms: previews keep coming, full only at rest."""
    shown = []

    def render(req: ViewRequest, should_stop) -> np.ndarray:
        time.sleep(0.04)
        return np.zeros((req.resolution, 1, 3), np.uint8)

    pr = ProgressiveRenderer(render, lambda img, req, full: shown.append((req.frame, full)), settle_s=0.1)
    try:
        for k in range(40):
            pr.update(request_looking_at((0, -2, 0), (0, 0, 0), resolution=64, frame=k))
            time.sleep(0.01)
        streamed = list(shown)
        deadline = time.monotonic() + 5
        while (39, True) not in shown and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        pr.stop()
    assert len(streamed) >= 4 and not any(full for _, full in streamed), "previews while the requests flow"
    assert shown[-1] == (39, True), "the last request at full quality once they stop"


def test_render_callback_draws_the_avatar(toy_fitted_project):
    from avatarctl.stages.view import ViewConfig, prepare

    setup = prepare(toy_fitted_project, ViewConfig(device="cpu", latent="mean"))
    s = setup.session
    assert [f.source for f in s.frames] == ["train", "train", "train", "test"]
    eye = np.asarray(setup.initial.position)
    req = request_looking_at(eye, setup.initial.look_at, setup.initial.up, resolution=48)
    img = s.render(req)
    assert img.shape == (36, 48, 3) and img.dtype == np.uint8
    centre, corner = img[12:24, 18:30].astype(float).mean(), img[:4, :4].astype(float).mean()
    assert centre > corner + 1, "the avatar is drawn in the middle"
    novel = s.render(request_looking_at(eye, setup.initial.look_at, setup.initial.up, resolution=48, frame=3))
    assert novel.shape == img.shape, "'mean' on a test frame falls back to z = 0 instead of failing"
    with pytest.raises(Cancelled):
        s.render(req, should_stop=lambda: True)


def test_a_motion_file_becomes_the_frame_list(toy_fitted_project, tmp_path):
    from fixtures.toy_capture import toy_motion

    from avatarctl.stages.view import ViewConfig, prepare

    toy_motion(5).save(tmp_path / "walk.npz")
    setup = prepare(toy_fitted_project, ViewConfig(device="cpu", poses=str(tmp_path / "walk.npz")))
    assert [f.source for f in setup.session.frames] == ["motion"] * 5
    req = request_looking_at(setup.initial.position, setup.initial.look_at, setup.initial.up, resolution=32, frame=4)
    assert setup.session.render(req).shape == (24, 32, 3)


@pytest.mark.browser
def test_viewer_page_in_headless_chromium(toy_fitted_project, tmp_path):
    pytest.importorskip("viser")
    from fixtures.browser import Browser, find_chromium, free_port

    if find_chromium() is None:
        pytest.skip("no chromium / chrome on this machine")
    from avatarctl.stages import view
    from avatarctl.stages.view import ViewConfig

    stop, urls, errors, results = threading.Event(), [], [], []

    def serve():
        try:
            results.append(view.run(toy_fitted_project, ViewConfig(port=free_port(), resolution=128, device="cpu"),
                                    ready=urls.append, stop=stop))
        except BaseException as e:  # noqa: BLE001 - reported by the test
            errors.append(e)

    th = threading.Thread(target=serve, daemon=True)
    th.start()
    browser = None
    try:
        deadline = time.monotonic() + 60
        while not urls and not errors and time.monotonic() < deadline:
            time.sleep(0.1)
        assert urls, f"viewer did not start: {errors}"
        browser = Browser(640, 480)
        browser.open(urls[0])
        drawn = None
        while time.monotonic() < deadline:
            time.sleep(1.0)
            shot = browser.screenshot()
            # the avatar: the centre of the page differs from the fit background (black) of the corners
            centre, corner = shot[200:280, 280:360].astype(float).mean(), shot[400:470, 100:200].astype(float).mean()
            if centre > corner + 10:
                drawn = shot
                break
        assert drawn is not None, "no avatar in the page's screenshot"
        import cv2

        cv2.imwrite(str(tmp_path / "viewer.png"), drawn[..., ::-1])
    finally:
        if browser is not None:
            browser.close()
        stop.set()
        th.join(10)
    assert not th.is_alive() and not errors, "the viewer stops cleanly"
    assert results[0].url == urls[0] and results[0].frames > 0 and results[0].config.resolution == 128


@pytest.mark.parametrize("fixture", ["toy_fitted_project", "toy_gaussian_project"])
def test_cli_prints_the_url_and_stops_cleanly_on_ctrl_c(fixture, request):
    """Both pages: viser's (ray-marched avatar) and ours (Gaussian-field avatar); the printed URL serves a page."""
    pytest.importorskip("viser")
    import urllib.request

    toy_fitted_project = request.getfixturevalue(fixture)
    import os
    import signal
    import subprocess
    import sys

    from fixtures.browser import free_port

    env = {**os.environ, "PYTHONUNBUFFERED": "1", "COLUMNS": "200"}
    proc = subprocess.Popen([sys.executable, "-m", "avatarctl.cli.app", "view", str(toy_fitted_project), "--device", "cpu",
                             "--port", str(free_port())], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env=env)
    lines = []
    try:
        deadline = time.monotonic() + 90
        while time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            lines.append(line)
            if "viewer ready" in line:
                break
        assert any("viewer ready: http://localhost:" in s for s in lines), "".join(lines)
        url = next(s for s in lines if "viewer ready:" in s).split("viewer ready:")[1].split()[0]
        with urllib.request.urlopen(url, timeout=10) as r:
            assert r.status == 200 and b"<html" in r.read(2000).lower()
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0 and "viewer stopped" in out and "Traceback" not in out, out


def test_a_gaussian_avatar_gives_the_page_its_splats(toy_gaussian_project, tmp_path):
    """Field "gaussians": the session hands out each frame's posed Gaussians (cached, encoded, by the controller),
    switches motions, and its
    server render is the rasterizer's exact image."""
    from fixtures.toy_capture import toy_motion

    from avatarctl.stages.view import PROJECT, ViewConfig, prepare

    setup = prepare(toy_gaussian_project, ViewConfig(device="cpu"))
    s = setup.session
    assert s.gaussian and s.motion.name == PROJECT and s.motion.fps > 0
    a, b = s.splats(0, "auto"), s.splats(3, "auto")
    assert a.count + a.dropped == 8 * 24 * 4 or a.count > 0
    assert a.centers.shape == (a.count, 3) and a.covariances.shape == (a.count, 3, 3)
    assert a.rgbs.shape == (a.count, 3) and a.opacities.shape == (a.count, 1)
    assert np.all(np.linalg.eigvalsh(a.covariances.astype(np.float64)) > 0), "covariances positive definite"
    assert 0 <= a.rgbs.min() and a.rgbs.max() <= 1 and a.opacities.min() >= 1 / 255
    from avatarctl.viewer.controller import FrameKey, ViewerController

    controller = ViewerController(s)  # the one cache of posed frames: the controller's, of encoded frames
    try:
        key = FrameKey(controller.state.generation, 0, "auto")
        assert controller.frame_data(key) is controller.frame_data(key), "cached per (frame, latent)"
    finally:
        controller.stop()
    assert not np.allclose(a.centers, b.centers), "another frame, another pose"
    req = request_looking_at(setup.initial.position, setup.initial.look_at, setup.initial.up, resolution=48)
    img = s.render(req)
    assert img.shape == (36, 48, 3) and img[12:24, 18:30].mean() != img[:4, :4].mean()
    toy_motion(5).save(tmp_path / "walk.npz")
    m = s.set_motion(str(tmp_path / "walk.npz"))
    assert [f.source for f in s.frames] == ["motion"] * 5 and m.name == str(tmp_path / "walk.npz")
    assert s.splats(4, "zero").count > 0
    with pytest.raises(Exception, match="no motion file"):
        s.set_motion(str(tmp_path / "missing.npz"))
    assert len(s.frames) == 5, "a failed load keeps the motion shown"


def test_the_wire_form_of_a_frame_keeps_its_gaussians(toy_gaussian_project):
    """`encode_splats` (22 bytes a Gaussian): centres within a 16-bit step of the box, covariances within float16
    precision, colours within a byte."""
    from avatarctl.stages.view import ViewConfig, prepare
    from avatarctl.viewer.splats import decode_splats, encode_splats

    a = prepare(toy_gaussian_project, ViewConfig(device="cpu")).session.splats(0, "auto")
    header, payload = encode_splats(a)
    assert len(payload) == 22 * a.count
    b = decode_splats(header, payload)
    step = (np.asarray(header["hi"]) - np.asarray(header["lo"])) / 65535
    assert np.all(np.abs(b.centers - a.centers) <= step * 0.5 + 1e-6)
    rel = np.abs(b.covariances - a.covariances).max(axis=(1, 2)) / np.abs(a.covariances).max(axis=(1, 2))
    assert rel.max() < 2e-3, rel.max()
    assert np.abs(b.rgbs - a.rgbs).max() <= 0.5 / 255 + 1e-6 and np.abs(b.opacities - a.opacities).max() <= 0.5 / 255 + 1e-6


def test_the_controller_plays_switches_and_poses_the_newest_frame(toy_gaussian_project, tmp_path):
    """One controller behind both pages: setters, play at the fps, motion switch, the posing thread's newest frame."""
    from fixtures.toy_capture import toy_motion

    from avatarctl.stages.view import PROJECT, ViewConfig, prepare
    from avatarctl.viewer.controller import ViewerController

    setup = prepare(toy_gaussian_project, ViewConfig(device="cpu"))
    started = []

    class Job:  # a "save video" that finishes at its third poll
        polls = 0

        def poll(self):
            self.polls += 1
            return "video saved: v.mp4" if self.polls >= 3 else None

        def progress(self):
            return f"{self.polls}/3 images"

        def cancel(self):
            pass

    def video(motion, latent, camera_path):
        started.append((motion, latent, camera_path))
        return Job()

    c = ViewerController(setup.session, fps=20.0, resolution=48, motions=(PROJECT,), video=video)
    states, frames = [], []
    c.subscribe(states.append)
    c.subscribe_frames(lambda key, splats: frames.append((key, splats.count)))
    try:
        c.set_frame(99)
        assert c.state.frame == len(c.state.labels) - 1, "clamped to the last frame"
        c.set_latent("zero")
        c.set_latent("bogus")
        assert c.state.latent == "zero" and "unknown latent" in c.state.status
        deadline = time.monotonic() + 20
        while (not frames or frames[-1][0] != c.state.key) and time.monotonic() < deadline:
            time.sleep(0.02)
        assert frames and frames[-1][0] == c.state.key and frames[-1][1] > 0, "the newest frame is posed"
        c.set_playing(True)
        time.sleep(0.6)
        c.set_playing(False)
        assert len({s.frame for s in states}) >= 3, "play advances the frames"
        toy_motion(5).save(tmp_path / "walk.npz")
        c.switch_motion(str(tmp_path / "walk.npz"), add=True)
        s = c.state
        assert len(s.labels) == 5 and s.generation == 1 and s.motion in s.motions and s.frame == 0
        c.switch_motion(str(tmp_path / "missing.npz"), add=True)
        assert "cannot load" in c.state.status and len(c.state.labels) == 5
        c.set_camera_path("orbit")
        c.start_video()
        assert started == [(s.motion, "zero", "orbit")] and not c.state.can_video
        deadline = time.monotonic() + 5
        while "video saved" not in c.state.status and time.monotonic() < deadline:
            time.sleep(0.02)
        assert "video saved: v.mp4" in c.state.status and c.state.can_video
        req = c.request(*_camera_of(setup.initial), aspect=4 / 3)
        assert c.render(req).shape == (36, 48, 3) and "exact render" in c.state.status
    finally:
        c.stop()


class _FakePosing:
    """A stand-in `ViewerSession` for the controller's posing thread: `splats` records each call and takes `delay`
    seconds; a frame in `gate` waits until `release()`. Four Gaussians a frame, their x the frame number."""

    gaussian = True

    def __init__(self, n: int = 40, fps: float = 0.5, delay: float = 0.0):
        from avatarctl.viewer.session import ViewerFrame, ViewerMotion

        self.motion = ViewerMotion("project", [ViewerFrame(f"frame {i}", i, "train") for i in range(n)],
                                   lambda i, latent: None, fps)
        self.load_motion = lambda name: ViewerMotion(name, [ViewerFrame(f"m {i}", i, "motion") for i in range(n)],
                                                     lambda i, latent: None, fps)
        self.delay, self.calls, self.gate, self._open = delay, [], set(), threading.Event()

    @property
    def frames(self):
        return self.motion.frames

    def set_motion(self, name):
        self.motion = self.load_motion(name)
        return self.motion

    def release(self):
        self._open.set()

    def splats(self, frame, latent):
        from avatarctl.viewer.splats import SplatFrame

        self.calls.append((frame, latent))
        if frame in self.gate:
            assert self._open.wait(10), "the test never released the gate"
        time.sleep(self.delay)
        g = 4
        return SplatFrame(centers=np.full((g, 3), float(frame), np.float32),
                          covariances=np.tile(np.eye(3, dtype=np.float32) * 1e-4, (g, 1, 1)),
                          rgbs=np.full((g, 3), 0.5, np.float32), opacities=np.ones((g, 1), np.float32))


def _wait(cond, timeout=10.0):
    deadline = time.monotonic() + timeout
    while not cond() and time.monotonic() < deadline:
        time.sleep(0.005)
    return cond()


def test_the_posing_thread_poses_ahead_while_playing_and_serves_the_clock_from_the_cache():
    """Playing, the frames the clock reaches next are posed and encoded before it gets there: the clock's next frame
    is shown from the cache, without a new posing call; paused, nothing is posed ahead; scrubbing back is a cache
    hit."""
    from avatarctl.viewer.controller import FrameKey, ViewerController
    from avatarctl.viewer.splats import decode_splats

    session = _FakePosing(fps=0.5)  # the clock would move every 2 s: the test moves it itself (`_update`)
    session.gate = {3}  # the third frame ahead hangs until released
    c = ViewerController(session, ahead=3)
    shown = []
    c.subscribe_frames(lambda key, data: shown.append((key, data)))
    try:
        assert _wait(lambda: shown) and shown[0][0] == FrameKey(0, 0, "auto")
        time.sleep(0.1)
        assert session.calls == [(0, "auto")], "paused: nothing posed ahead"
        c.set_playing(True)
        assert _wait(lambda: len(session.calls) == 4)
        assert [f for f, _ in session.calls] == [0, 1, 2, 3], "the clock's next 3 frames, in order"
        assert c.ahead_keys() == [FrameKey(0, f, "auto") for f in (1, 2, 3)]
        c._update(frame=1)  # the play clock reaches frame 1 while frame 3 is being posed
        assert len(shown) == 2 and shown[1][0] == FrameKey(0, 1, "auto"), "shown at once, from the cache"
        assert decode_splats(shown[1][1].header, shown[1][1].payload).centers[0, 0] == pytest.approx(1.0, abs=1e-3)
        session.release()
        assert _wait(lambda: len(session.calls) == 5)
        assert session.calls[-1] == (4, "auto"), "one more frame ahead; frame 1 itself was not posed again"
        c.set_playing(False)
        c.set_frame(0)  # scrubbing back over recent frames
        assert _wait(lambda: shown[-1][0].frame == 0)
        c.set_frame(2)
        assert _wait(lambda: shown[-1][0].frame == 2)
        time.sleep(0.05)
        assert len(session.calls) == 5, "recent frames come from the cache"
    finally:
        c.stop()


def test_the_look_ahead_stride_follows_the_cost_of_posing():
    """Posing slower than the clock: the look-ahead skips the frames the clock would pass while posing."""
    from avatarctl.viewer.controller import ViewerController

    c = ViewerController(_FakePosing(fps=20.0), ahead=3)
    try:
        c.pose_seconds = 0.12  # 2.4 frames of the clock a posing (2.64 with the margin)
        c._update(playing=True, frame=10)
        assert [k.frame for k in c.ahead_keys()] == [13, 14, 15]
        c.pose_seconds = 0.01
        assert [k.frame for k in c.ahead_keys(c.state)] == [11, 12, 13]
        c._update(frame=38)
        assert [k.frame for k in c.ahead_keys()] == [39, 0, 1], "the motion loops"
    finally:
        c.stop()


def test_a_frame_asked_for_is_posed_before_pending_look_ahead():
    """Newest wins: while a look-ahead frame is being posed, a frame set on the slider is posed next, before the
    look-ahead frames still pending."""
    from avatarctl.viewer.controller import ViewerController

    session = _FakePosing(fps=0.5)
    session.gate = {1}  # the first look-ahead frame hangs until released
    c = ViewerController(session, ahead=3)
    shown = []
    c.subscribe_frames(lambda key, data: shown.append(key.frame))
    try:
        assert _wait(lambda: shown == [0])
        c.set_playing(True)
        assert _wait(lambda: session.calls[-1:] == [(1, "auto")])
        c.set_frame(20)  # asked for while frame 1 is being posed ahead
        session.release()
        assert _wait(lambda: 20 in shown and len(session.calls) >= 3)
        assert [f for f, _ in session.calls[:3]] == [0, 1, 20], "the slider's frame before any pending look-ahead"
        assert _wait(lambda: len(session.calls) == 6)
        assert [f for f, _ in session.calls[3:]] == [21, 22, 23], "then ahead of the frame asked for"
        assert shown == [0, 20], "the look-ahead frame finished behind the new frame is not shown"
    finally:
        c.stop()


def test_the_frame_cache_is_bounded_and_emptied_when_the_posed_gaussians_change(tmp_path):
    """The LRU of encoded frames keeps at most its frames and bytes; a new latent mode, motion or motion file
    empties it (and a frame posed before that is not stored)."""
    from avatarctl.viewer.controller import FrameCache, FrameKey, ViewerController
    from avatarctl.viewer.splats import EncodedSplats

    data = EncodedSplats({"count": 1}, b"x" * 100)
    cache = FrameCache(max_frames=3, max_bytes=250)
    for f in range(3):
        cache.put(FrameKey(0, f, "auto"), data)
    assert [k.frame for k in cache.keys()] == [1, 2] and cache.nbytes == 200, "250 bytes hold two frames"
    cache.max_bytes = 10_000
    cache.get(FrameKey(0, 1, "auto"))
    for f in (3, 4):
        cache.put(FrameKey(0, f, "auto"), data)
    assert [k.frame for k in cache.keys()] == [1, 3, 4], "three frames at most, the least recently used dropped"
    epoch = cache.epoch
    cache.clear()
    cache.put(FrameKey(0, 5, "auto"), data, epoch)
    assert len(cache) == 0 and cache.nbytes == 0, "a frame posed before the clear is not stored"

    session = _FakePosing(fps=0.5)
    c = ViewerController(session, ahead=3, cache_frames=4)
    c.subscribe_frames(lambda key, data: None)
    try:
        c.set_playing(True)
        assert _wait(lambda: len(session.calls) == 4)
        for f in range(1, 12):  # the clock moves on: the look-ahead keeps posing, the cache keeps 4
            c._update(frame=f)
            assert _wait(lambda f=f: len(session.calls) == 4 + f)
            assert len(c.cache) <= 4
        assert len(c.cache) == 4
        c.set_latent("zero")
        assert all(k.latent == "zero" for k in c.cache.keys())
        assert _wait(lambda: session.calls[-1][1] == "zero")
        c.switch_motion("walk.npz", add=True)
        assert c.state.generation == 1
        assert all(k.generation == 1 for k in c.cache.keys())
        c.set_frame(3)
        assert _wait(lambda: FrameKey(1, 3, "zero") in c.cache)
        assert session.calls[-1] == (3, "zero"), "the new motion's frame is posed anew"
    finally:
        c.stop()


def _camera_of(initial):
    """(wxyz, position, fov_y) of a camera at `initial` looking at its subject."""
    R, _ = look_at(np.asarray(initial.position, float), np.asarray(initial.look_at, float),
                   np.asarray(initial.up, float))
    return _wxyz(R.T), tuple(initial.position), 0.8


def _page_errors(browser) -> list:
    return [m for m in browser.events if m.get("method") == "Runtime.exceptionThrown"
            or (m.get("method") == "Runtime.consoleAPICalled" and m["params"].get("type") == "error")
            or (m.get("method") == "Log.entryAdded" and m["params"]["entry"].get("level") == "error")]


def _gaussian_page_server(project):
    """Our page for the Gaussian-field avatar of `project`, served in this process at 64 px exact renders."""
    from fixtures.browser import free_port

    from avatarctl.stages.view import PROJECT, ViewConfig, prepare
    from avatarctl.viewer.controller import ViewerController
    from avatarctl.viewer.splat_server import SplatPageServer

    setup = prepare(project, ViewConfig(device="cpu"))
    controller = ViewerController(setup.session, resolution=64, motions=(PROJECT,))
    return SplatPageServer(controller, setup.initial, port=free_port())


@pytest.mark.browser
def test_gaussian_viewer_page_draws_changes_plays_and_renders_in_headless_chromium(toy_gaussian_project, tmp_path):
    """Our page for a Gaussian-field avatar: the browser draws the avatar, a frame change changes the picture, play
    shows new frames, "render" shows the server's image, the panel's controls reach the server, no console error."""
    pytest.importorskip("websockets")
    from fixtures.browser import Browser, find_chromium
    from fixtures.toy_capture import toy_motion

    if find_chromium() is None:
        pytest.skip("no chromium / chrome on this machine")
    from benchmarks.viewer_page import canvas_rect, evaluate, wait_drawn, wait_for

    server = _gaussian_page_server(toy_gaussian_project)
    controller = server.controller
    browser = None
    toy_motion(5).save(tmp_path / "walk.npz")

    def wait(expr: str, timeout: float = 30.0):
        return wait_for(browser, expr, timeout)

    try:
        browser = Browser(640, 480)
        browser.call("Runtime.enable")
        browser.call("Log.enable")
        browser.open(server.url)
        first = wait_drawn(browser)
        assert first is not None, "no avatar in the page's screenshot"
        x, y, w, h = canvas_rect(browser)
        wait("window.__viewer.shown && window.__viewer.shown.frame === 0")
        last = len(controller.state.labels) - 1
        controller.set_frame(last)
        wait(f"window.__viewer.shown.frame === {last}")
        time.sleep(0.3)
        changed = browser.screenshot()
        diff = np.abs(changed[y:y + h, x:x + w].astype(float) - first[y:y + h, x:x + w].astype(float)).mean()
        assert diff > 0.05, f"another frame, another picture ({diff})"
        assert evaluate(browser, "document.getElementById('label').textContent").startswith(
            controller.state.labels[last])
        evaluate(browser, "document.getElementById('play').click()")
        wait("window.__viewer.state.playing")
        seen = set()
        deadline = time.monotonic() + 3.0
        while time.monotonic() < deadline:
            seen.add(evaluate(browser, "window.__viewer.shown.frame"))
            time.sleep(0.05)
        evaluate(browser, "document.getElementById('play').click()")
        assert len(seen) >= 2 and len(server.pushes) >= 3, f"play shows frames: {seen}"
        wait("!window.__viewer.state.playing && window.__viewer.shown.frame === window.__viewer.state.frame")
        evaluate(browser, "document.getElementById('render').click()")
        wait("window.__viewer.exactShown && document.getElementById('exact').naturalWidth > 0", 60)
        size = evaluate(browser, "[document.getElementById('exact').naturalWidth, "
                                 "document.getElementById('exact').naturalHeight]")
        assert max(size) == 64, f"the server image at the resolution asked for: {size}"
        assert "exact render" in controller.state.status
        rendered = browser.screenshot()
        cv2 = pytest.importorskip("cv2")
        for name, img in (("first", first), ("changed", changed), ("rendered", rendered)):
            cv2.imwrite(str(tmp_path / f"page_{name}.png"), img[..., ::-1])
        evaluate(browser, "const l = document.getElementById('latent'); l.value = 'zero';"
                          " l.dispatchEvent(new Event('change'))")
        wait("window.__viewer.state.latent === 'zero' && window.__viewer.shown.latent === 'zero'")
        assert controller.state.latent == "zero"
        assert not evaluate(browser, "window.__viewer.exactShown"), "the exact image goes with the frame it showed"
        evaluate(browser, f"document.getElementById('file').value = {json.dumps(str(tmp_path / 'walk.npz'))};"
                          " document.getElementById('load').click()")
        wait("window.__viewer.state.labels.length === 5 && window.__viewer.shown.generation === 1")
        second = browser.new_tab(server.url)
        try:
            assert wait_drawn(second) is not None, "a second tab draws too"
        finally:
            second.close()
        assert not _page_errors(browser), _page_errors(browser)
    finally:
        if browser is not None:
            browser.close()
        server.stop()


@pytest.mark.browser
def test_gaussian_viewer_page_draws_a_splat_budget_while_moving(toy_gaussian_project):
    """The splat budget (splat.webgl, "fast preview while moving"): with a slow measured draw the budget drops, the
    drag draws fewer Gaussians, the rest draws all and equals the picture with the budget off; the status says it."""
    pytest.importorskip("websockets")
    from fixtures.browser import Browser, find_chromium

    if find_chromium() is None:
        pytest.skip("no chromium / chrome on this machine")
    from benchmarks.viewer_page import canvas_rect, drag, evaluate, wait_drawn, wait_for

    server = _gaussian_page_server(toy_gaussian_project)
    browser = None

    def wait(expr: str, timeout: float = 30.0):
        return wait_for(browser, expr, timeout)

    def redraw_at_rest():  # a moving draw, then the full one at rest (timed: the budget follows)
        evaluate(browser, "window.__splatStats.drawn = -1; window.__viewer.renderer.moved()")
        wait("window.__splatStats.drawn === window.__splatStats.gaussians && !window.__viewer.renderer.moving")

    try:
        browser = Browser(640, 480)
        browser.call("Runtime.enable")
        browser.call("Log.enable")
        browser.open(server.url)
        assert wait_drawn(browser) is not None
        wait("window.__viewer.shown && window.__splatStats.gaussians > 0")
        n = evaluate(browser, "window.__splatStats.gaussians")
        evaluate(browser, "window.__viewer.renderer.lod.minSplats = 64")
        redraw_at_rest()
        fast = evaluate(browser, "window.__viewer.renderer.budget")
        evaluate(browser, "window.__viewer.renderer.lod.measureScale = 1e4")  # a machine 10^4 times slower
        redraw_at_rest()
        redraw_at_rest()
        slow = evaluate(browser, "window.__viewer.renderer.budget")
        assert 64 <= slow < n and slow < fast, f"a slow machine, a smaller budget: {fast} -> {slow} of {n}"
        x, y, w, h = rect = canvas_rect(browser)
        drag(browser, 1.0, rect)
        stats = evaluate(browser, "window.__splatStats")
        assert stats["moving"] == slow, f"the drag draws the budget: {stats}"
        wait(f"window.__splatStats.drawn === {n}")
        time.sleep(0.3)
        rest = browser.screenshot()[y:y + h, x:x + w].astype(float)
        evaluate(browser, "window.__viewer.renderer.lod.holdPreview = true")
        wait(f"window.__splatStats.drawn === {slow}")
        wait("document.getElementById('status').textContent.includes("
             f"'preview {slow:,} / {n:,} splats while moving')")
        time.sleep(0.3)
        preview = browser.screenshot()[y:y + h, x:x + w].astype(float)
        assert np.abs(preview - rest).mean() > 0.05, "the preview leaves Gaussians out"
        evaluate(browser, "window.__viewer.renderer.lod.holdPreview = false")
        wait(f"window.__splatStats.drawn === {n}")
        evaluate(browser, "document.getElementById('lod').click()")
        assert evaluate(browser, "window.__viewer.renderer.lod.enabled") is False
        drag(browser, 0.5, rect)
        assert evaluate(browser, "window.__splatStats.moving") == n, "the budget off: all drawn while moving"
        wait(f"window.__splatStats.drawn === {n} && !window.__viewer.renderer.moving")
        time.sleep(0.3)
        evaluate(browser, "window.__splatStats.drawn = -1; window.__viewer.renderer.moved()")  # the same view again
        wait(f"window.__splatStats.drawn === {n}")
        drawn_without = browser.screenshot()[y:y + h, x:x + w].astype(float)
        evaluate(browser, "window.__splatStats.drawn = -1; document.getElementById('lod').click()")  # on, at rest
        wait(f"window.__splatStats.drawn === {n}")
        time.sleep(0.3)
        rest_again = browser.screenshot()[y:y + h, x:x + w].astype(float)
        assert np.abs(rest_again - drawn_without).max() <= 2, "at rest the budget draws the no-budget picture"
        assert not _page_errors(browser), _page_errors(browser)
    finally:
        if browser is not None:
            browser.close()
        server.stop()


def test_the_benchmarks_slow_server_waits_then_poses_through():
    """`benchmarks.viewer_page --pose-delay-ms`: the wrapped posing waits the delay, then returns what the posing
    returns, with its arguments."""
    import time

    from benchmarks.viewer_page import slowed

    calls = []
    slow = slowed(lambda *a, **k: calls.append((a, k)) or "posed", 0.05)
    t0 = time.perf_counter()
    assert slow(1, latent="auto") == "posed"
    assert time.perf_counter() - t0 >= 0.05 and calls == [((1,), {"latent": "auto"})]


@pytest.mark.browser
def test_gaussian_viewer_page_measured_at_toy_scale(toy_gaussian_project, tmp_path):
    """benchmarks/viewer_page.py at toy scale: the drag turns the view, frame changes and playback show frames, a
    second tab draws too, memory stays small."""
    pytest.importorskip("websockets")
    from fixtures.browser import Browser, find_chromium

    if find_chromium() is None:
        pytest.skip("no chromium / chrome on this machine")
    from benchmarks.viewer_page import measure, rss_mb, start_viewer

    before = rss_mb()  # this test process holds what the suite's earlier tests left: count the viewer's growth
    server = start_viewer(toy_gaussian_project, device="cpu")
    browser = None
    try:
        browser = Browser(640, 480)
        fig = measure(server, browser, seconds=2.0, shots=tmp_path, changes=3)
    finally:
        if browser is not None:
            browser.close()
        server.stop()
    assert fig.orbit.image_change > 0.5, "dragging turns the view (drawn by the page)"
    assert fig.orbit.fps > 0 and fig.orbit.drawn_fps > 0 and fig.frame_change_ms, fig
    assert fig.playback_fps_page > 0 and fig.playback_pushes_per_s > 0, fig
    assert fig.second_tab_drawn and fig.peak_rss_mb - before < 1024, fig
