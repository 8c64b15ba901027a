"""The viewer page of a Gaussian-field avatar measured in headless Chromium (SwiftShader WebGL: a CPU floor).

Starts `avatarctl view`'s server in this process (`stages.view.prepare`, a `viewer.controller.ViewerController` and
the page the viewer serves for a Gaussian-field avatar, `viewer.splat_server.SplatPageServer`), opens the page, and measures in the browser, with a probe injected into the page (a `requestAnimationFrame` loop that counts
animation frames and the frames in which the page issued WebGL draw calls, and, when sampling, draws the WebGL canvas
into a 24x18 canvas and notes the wall time whenever it changes):
- **orbit fps**: animation frames per second while the mouse drags the orbit camera (Chromium input events), with
  sampling off (reading the canvas back costs SwiftShader frames); beside it the frames that drew, the browser's CPU
  time per drawn frame (all of Chromium's processes, from /proc: the figure least moved by other jobs on a shared
  machine; 1000 / it is the fps of one free core) and the mean change of one screenshot before and one after the
  drag (> 0: the view really turned);
- **frame-change latency**: wall time from setting the frame on the server (`ViewerController.set_frame`, what
  the page's slider sends) to the first animation frame whose canvas differs (posing, encoding, sending, the page's
  decode, sort and draw; same clock, one machine); beside it the server's share (posing + encoding, uncached);
- **playback fps**: distinct canvas images per second while "play" runs (the frames of motion actually shown), and
  the server's pushes per second;
- **memory**: the peak resident memory of this process (the viewer's: model, caches, server), from /proc;
- **second tab**: a second page of the same browser shows the avatar too;
- the 1-minute load average at the start of each measurement.

With `--player FILE` (an `export --format player` page) the same browser also measures that page, alternating with
the viewer's page `--repeats` times (paired figures on a shared machine): orbit as above, and frame change as the
wall time from moving the page's slider to the first changed canvas.

    python -m benchmarks.viewer_page PROJECT [--seconds 5] [--size 640 480] [--out figures.json] [--shots DIR]
                                     [--player player.html] [--repeats 2] [--budget on off] [--pose-delay-ms 80]

`--budget on off` measures with the pages' splat budget while moving ("fast preview while moving", `splat.webgl`) on
and off, alternating; with it on, also the Gaussians drawn during the drag and at rest, the frame change until all
Gaussians are drawn again, and the PSNR of the preview against the image at rest (screenshots `viewer_moving.png`,
`viewer_rest.png` with `--shots`).

`--pose-delay-ms D` emulates a slow server (the posing of a loaded machine): every posing (the model's
`posed_gaussians`, which `ViewerSession.splats` calls each time; the viewer poses a frame only when it is not in the
controller's `FrameCache`) waits D ms more, through a wrapper this benchmark puts on its model object (the viewer
itself has no such option). The cache works as without it: a frame posed once costs no posing again while cached.

The viewer shows the project's own frames (`avatarctl view` without `--poses`; on synth small's project: 120 frames
at 15 fps, so `--seconds 5` of play passes 75 of them); the benchmark has no option for a motion file.

Needs websockets (the `view` extra) and Chromium (`apt-get install -y chromium`). Run it with `nice -n 19` on a shared machine.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

PROBE = """
(() => {
  if (window.__probe) return true;
  const p = {frames: 0, drawn: 0, draws: 0, seen: 0, changes: [], sig: null, sample: false};
  for (const P of [WebGL2RenderingContext.prototype, WebGLRenderingContext.prototype])
    for (const m of ['drawArrays', 'drawElements', 'drawArraysInstanced', 'drawElementsInstanced']) {
      const f = P[m];
      P[m] = function (...a) { p.draws++; return f.apply(this, a); };
    }
  const small = document.createElement('canvas'); small.width = 24; small.height = 18;
  const ctx = small.getContext('2d', {willReadFrequently: true});
  function gl() {
    let best = null;
    for (const c of document.querySelectorAll('canvas'))
      if (!best || c.width * c.height > best.width * best.height) best = c;
    return best;
  }
  function tick() {
    p.frames++;
    if (p.draws !== p.seen) { p.drawn++; p.seen = p.draws; }
    const c = gl();
    if (p.sample && c && c.width > 0) {
      ctx.drawImage(c, 0, 0, 24, 18);
      const d = ctx.getImageData(0, 0, 24, 18).data;
      let h = 0;
      for (let i = 0; i < d.length; i += 4) h = (Math.imul(h, 31) + d[i] + 7 * d[i + 1] + 13 * d[i + 2]) | 0;
      if (h !== p.sig) { p.sig = h; p.changes.push(Date.now()); }
    }
    requestAnimationFrame(tick);
  }
  requestAnimationFrame(tick);
  window.__probe = p;
  return true;
})()
"""


@dataclass
class OrbitFigures:
    fps: float  # animation frames per second during the drag (no canvas sampling)
    drawn_fps: float  # animation frames per second in which the page issued WebGL draw calls
    cpu_ms_per_frame: float  # CPU time of all Chromium processes per drawn frame
    image_change: float  # mean |difference| of the canvas, one screenshot before and one after the drag (0..255)
    load_average: float  # 1-minute load average when the drag started
    splats_moving: int  # Gaussians in the last draw during the drag (the splat budget, splat.webgl)
    splats_rest: int  # Gaussians in the draw after the drag, at rest
    us_per_splat: float | None  # the renderer's estimate of a drawn splat's cost (None: the budget is off)


@dataclass
class PageFigures:
    budget: bool  # the page's "fast preview while moving" (SplatRenderer.lod.enabled)
    gaussians: int  # Gaussians sent per frame
    load_average: float  # 1-minute load average at the start
    orbit: OrbitFigures
    idle_changes_per_s: float  # canvas changes per second with nothing happening (0: the latency probe is clean)
    frame_change_ms: list[float]  # per frame change, slider set -> canvas changed
    frame_change_full_ms: list[float]  # slider set -> the last canvas change within 0.6 s (all splats drawn)
    preview_psnr_db: float | None  # the canvas drawn with the budget against the canvas at rest (same view; None:
    # the budget off or covering all Gaussians)
    playback_fps_page: float  # distinct canvas images per second while playing
    playback_pushes_per_s: float  # frames the server sent per second while playing
    motion_fps: float
    peak_rss_mb: float
    second_tab_drawn: bool
    splat_seconds: float  # posing + arrays of one uncached frame on the server
    encode_seconds: float  # its wire form (splats.encode_splats)
    bytes_per_frame: int  # the binary message of one frame


@dataclass
class PlayerFigures:
    budget: bool
    load_average: float
    orbit: OrbitFigures
    frame_change_ms: list[float]  # per slider move in the page -> canvas changed


def browser_cpu_seconds(tab: Any) -> float:
    """User + system CPU seconds of the browser's process and all its descendants (/proc)."""
    root = getattr(tab, "browser", tab).proc.pid
    pids, todo = [root], [root]
    while todo:
        pid = todo.pop()
        try:
            for task in os.listdir(f"/proc/{pid}/task"):
                kids = [int(c) for c in Path(f"/proc/{pid}/task/{task}/children").read_text().split()]
                pids += kids
                todo += kids
        except OSError:  # a process that ended meanwhile
            pass
    ticks = 0
    for pid in pids:
        try:
            fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
            ticks += int(fields[11]) + int(fields[12])
        except OSError:
            pass
    return ticks / os.sysconf("SC_CLK_TCK")


def load_average() -> float:
    return round(os.getloadavg()[0], 2)


def reset_peak_rss() -> None:
    """Start the peak-RSS count (VmHWM) afresh (Linux: `5` written to /proc/self/clear_refs), so that `peak_rss_mb`
    is the viewer's own peak, not that of what ran before it in this process (a test suite); a no-op elsewhere."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        pass


def _status_mb(key: str) -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def peak_rss_mb() -> float:
    """This process's peak resident memory (VmHWM), MB."""
    return _status_mb("VmHWM")


def rss_mb() -> float:
    """This process's resident memory now (VmRSS), MB."""
    return _status_mb("VmRSS")


def evaluate(tab: Any, expr: str) -> Any:
    return tab.call("Runtime.evaluate", expression=expr, returnByValue=True)["result"].get("value")


def wait_for(tab: Any, expr: str, timeout: float = 30.0) -> Any:
    """The value of the page expression `expr` once it is truthy (polled every 50 ms); AssertionError after
    `timeout` seconds."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = evaluate(tab, expr)
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError(f"timed out waiting for {expr}")


CANVAS_RECT = """
(() => { let best = null;
  for (const c of document.querySelectorAll('canvas'))
    if (!best || c.width * c.height > best.width * best.height) best = c;
  if (!best) return null; const r = best.getBoundingClientRect();
  return [Math.round(r.left), Math.round(r.top), Math.round(r.width), Math.round(r.height)]; })()
"""


def canvas_rect(tab: Any) -> tuple[int, int, int, int] | None:
    """(left, top, width, height) of the page's WebGL canvas, CSS pixels."""
    rect = evaluate(tab, CANVAS_RECT)
    return tuple(rect) if rect and rect[2] > 0 and rect[3] > 0 else None


def drag(tab: Any, seconds: float, rect: tuple[int, int, int, int]) -> int:
    """Drag the orbit camera left and right over the canvas for `seconds` (mouse events, DevTools protocol)."""
    cx, cy = rect[0] + rect[2] // 2, rect[1] + rect[3] // 2
    tab.call("Input.dispatchMouseEvent", type="mouseMoved", x=cx, y=cy)
    tab.call("Input.dispatchMouseEvent", type="mousePressed", x=cx, y=cy, button="left", clickCount=1)
    t0, k = time.monotonic(), 0
    while time.monotonic() - t0 < seconds:
        x = cx + int(120 * np.sin(k * 0.05))
        tab.call("Input.dispatchMouseEvent", type="mouseMoved", x=x, y=cy, button="left", buttons=1)
        k += 1
        time.sleep(0.008)
    tab.call("Input.dispatchMouseEvent", type="mouseReleased", x=cx, y=cy, button="left", clickCount=1)
    return k


def orbit(tab: Any, seconds: float) -> OrbitFigures:
    """Drag the orbit camera for `seconds` with the probe's sampling off (`PageFigures.orbit`)."""
    evaluate(tab, "window.__probe.sample = false")
    rect = canvas_rect(tab)
    x, y, w, h = rect
    load = load_average()
    before = tab.screenshot()[y:y + h, x:x + w].astype(np.float32)
    c0, (f0, d0), t0 = browser_cpu_seconds(tab), evaluate(tab, "[window.__probe.frames, window.__probe.drawn]"), \
        time.monotonic()
    drag(tab, seconds, rect)
    (f1, d1), t1, c1 = evaluate(tab, "[window.__probe.frames, window.__probe.drawn]"), time.monotonic(), \
        browser_cpu_seconds(tab)
    moving = evaluate(tab, "window.__splatStats.moving")
    time.sleep(0.5)
    after = tab.screenshot()[y:y + h, x:x + w].astype(np.float32)
    stats = evaluate(tab, "window.__splatStats")
    return OrbitFigures(fps=round((f1 - f0) / (t1 - t0), 2), drawn_fps=round((d1 - d0) / (t1 - t0), 2),
                        cpu_ms_per_frame=round(1000.0 * (c1 - c0) / max(d1 - d0, 1), 1),
                        image_change=round(float(np.abs(after - before).mean()), 2), load_average=load,
                        splats_moving=int(moving), splats_rest=int(stats["rest"]), us_per_splat=stats["usPerSplat"])


SET_BUDGET = """
(on => { const b = document.getElementById('lod'); if (b.checked !== on) b.click(); return b.checked; })
"""

HOLD_PREVIEW = """
(hold => { window.__splatStats.drawn = -1; const r = (window.__viewer || window.__player).renderer;
  r.lod.holdPreview = hold; r.moved(); return true; })
"""


def preview_and_rest(tab: Any) -> tuple[np.ndarray, np.ndarray]:
    """Screenshots of the canvas drawn with the splat budget (held) and at rest, the same view and frame."""
    x, y, w, h = canvas_rect(tab)
    shots = []
    for hold in (True, False):
        evaluate(tab, f"{HOLD_PREVIEW}({'true' if hold else 'false'})")
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            st = evaluate(tab, "window.__splatStats")
            if st["drawn"] == (st["budget"] if hold else st["gaussians"]):
                break
            time.sleep(0.05)
        time.sleep(0.4 if hold else 0.1)
        shots.append(tab.screenshot()[y:y + h, x:x + w])
    return shots[0], shots[1]


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(((a.astype(np.float64) - b.astype(np.float64)) ** 2).mean())
    return round(10.0 * np.log10(255.0 ** 2 / max(mse, 1e-12)), 2)


def wait_drawn(tab: Any, timeout: float = 60.0) -> np.ndarray | None:
    """A screenshot once the centre of the canvas differs from its bottom-right corner (the avatar drawn), else
    None."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        rect = canvas_rect(tab)
        if rect is None:
            time.sleep(0.5)
            continue
        shot = tab.screenshot()
        x, y, w, h = rect
        view = shot[y:y + h, x:x + w]
        centre = view[h // 3:2 * h // 3, w // 3:2 * w // 3].astype(float)
        corner = view[-h // 8:, -w // 8:].astype(float)
        if np.abs(centre.mean(axis=(0, 1)) - corner.mean(axis=(0, 1))).max() > 8:
            return shot
        time.sleep(0.5)
    return None


def measure(server: Any, browser: Any, seconds: float = 5.0, size: tuple[int, int] = (640, 480),
            shots: Path | None = None, changes: int = 8, budget: bool = True) -> PageFigures:
    """The figures of the module docstring for a running `SplatPageServer` (`start_viewer`) and a `Browser`
    (tests/fixtures/browser.py) whose page is not yet opened; `budget`: the page's "fast preview while moving"."""
    from avatarctl.viewer.splats import encode_splats

    session, controller = server.session, server.controller
    load = load_average()
    t = time.perf_counter()
    splats = session.splats(len(session.frames) - 1, "zero")
    splat_seconds = time.perf_counter() - t
    t = time.perf_counter()
    header, payload = encode_splats(splats)
    encode_seconds = time.perf_counter() - t
    browser.open(server.url)
    first = wait_drawn(browser)
    if first is None:
        raise RuntimeError("the page never showed the avatar")
    evaluate(browser, f"{SET_BUDGET}({'true' if budget else 'false'})")
    evaluate(browser, PROBE)
    time.sleep(1.0)
    orbit_figures = orbit(browser, seconds)
    evaluate(browser, "window.__probe.sample = true")
    orbited = browser.screenshot()
    # frame changes: slider set on the server -> the first canvas change in the page
    n = len(session.frames)
    time.sleep(1.0)
    evaluate(browser, "window.__probe.changes = []")
    time.sleep(2.0)
    idle = len(evaluate(browser, "window.__probe.changes")) / 2.0
    latencies, full = [], []
    for k in range(changes):
        time.sleep(0.6)
        evaluate(browser, "window.__probe.changes = []")
        time.sleep(0.2)
        settled = len(evaluate(browser, "window.__probe.changes"))
        t_set = time.time() * 1000.0
        controller.set_frame((controller.state.frame + max(1, n // (changes + 1))) % n)
        deadline = time.monotonic() + 5
        seen = []
        while time.monotonic() < deadline:
            seen = evaluate(browser, "window.__probe.changes")
            if any(c >= t_set for c in seen[settled:]):
                break
            time.sleep(0.01)
        after = [c for c in seen[settled:] if c >= t_set]
        if after:
            latencies.append(float(after[0] - t_set))
            time.sleep(0.6)
            full.append(float(max(c for c in evaluate(browser, "window.__probe.changes") if c >= t_set) - t_set))
    sampled = budget and evaluate(browser, "window.__splatStats.budget < window.__splatStats.gaussians")
    preview, rest = preview_and_rest(browser) if sampled else (None, None)
    # playback
    evaluate(browser, "window.__probe.changes = []")
    pushes0 = len(server.pushes)
    tp = time.monotonic()
    controller.set_playing(True)
    time.sleep(seconds)
    controller.set_playing(False)
    played = time.monotonic() - tp
    shown = evaluate(browser, "window.__probe.changes")
    pushed = [t for t, _ in server.pushes[pushes0:]]
    playback_page = (len(shown) - 1) / ((shown[-1] - shown[0]) / 1000.0) if len(shown) > 2 else 0.0
    pushes_per_s = (len(pushed) - 1) / (pushed[-1] - pushed[0]) if len(pushed) > 2 else 0.0
    # a second tab
    second = browser.new_tab(server.url)
    drawn2 = wait_drawn(second)
    if shots is not None:
        import cv2

        shots.mkdir(parents=True, exist_ok=True)
        for name, img in (("start", first), ("orbited", orbited), ("second_tab", drawn2), ("moving", preview),
                          ("rest", rest)):
            if img is not None:
                cv2.imwrite(str(shots / f"viewer_{name}.png"), img[..., ::-1])
    second.close()
    return PageFigures(budget=budget, gaussians=splats.count, load_average=load, orbit=orbit_figures,
                       idle_changes_per_s=idle,
                       frame_change_ms=[round(x, 1) for x in latencies],
                       frame_change_full_ms=[round(x, 1) for x in full],
                       preview_psnr_db=psnr(preview, rest) if sampled else None,
                       playback_fps_page=round(playback_page, 2), playback_pushes_per_s=round(pushes_per_s, 2),
                       motion_fps=float(controller.state.fps), peak_rss_mb=round(peak_rss_mb(), 1),
                       second_tab_drawn=drawn2 is not None, splat_seconds=round(splat_seconds, 4),
                       encode_seconds=round(encode_seconds, 4), bytes_per_frame=len(payload) + 64)


SEEK = """
(() => { const seek = document.getElementById('seek'); const n = Number(seek.max) + 1;
  window.__probe.changes = []; const t = Date.now();
  seek.value = String((Number(seek.value) + Math.max(1, Math.floor(n / 3))) % n);
  seek.dispatchEvent(new Event('input')); return t; })()
"""


def measure_player(browser: Any, page: Path, seconds: float = 5.0, changes: int = 6,
                   budget: bool = True) -> PlayerFigures:
    """Orbit and frame-change figures of an `export --format player` page (paused) in `browser`."""
    load = load_average()
    browser.open(page.resolve().as_uri())
    if wait_drawn(browser) is None:
        raise RuntimeError(f"the player {page} never showed the avatar")
    evaluate(browser, "window.__player.setPlaying(false)")
    evaluate(browser, f"{SET_BUDGET}({'true' if budget else 'false'})")
    evaluate(browser, PROBE)
    time.sleep(1.0)
    orbit_figures = orbit(browser, seconds)
    evaluate(browser, "window.__probe.sample = true")
    latencies = []
    for _ in range(changes):
        time.sleep(0.6)
        t_set = evaluate(browser, SEEK)
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline:
            after = [c for c in evaluate(browser, "window.__probe.changes") if c >= t_set]
            if after:
                latencies.append(float(after[0] - t_set))
                break
            time.sleep(0.01)
    return PlayerFigures(budget=budget, load_average=load, orbit=orbit_figures, frame_change_ms=latencies)


def slowed(pose: Any, delay_s: float) -> Any:
    """`pose(...)` that waits `delay_s` first (`--pose-delay-ms`)."""

    def slow(*args: Any, **kwargs: Any) -> Any:
        time.sleep(delay_s)
        return pose(*args, **kwargs)

    return slow


def start_viewer(project: Path, device: str = "cpu", port: int = 0, pose_delay_ms: float = 0.0) -> Any:
    """The page `avatarctl view` serves for a Gaussian-field avatar, started in this process (`stop()` it);
    `pose_delay_ms`: module docstring. The peak-RSS count starts here (`reset_peak_rss`)."""
    from avatarctl.stages.view import PROJECT, ViewConfig, prepare
    from avatarctl.viewer.controller import ViewerController
    from avatarctl.viewer.splat_server import SplatPageServer

    reset_peak_rss()
    setup = prepare(project, ViewConfig(device=device))
    if pose_delay_ms > 0:
        model = setup.session.model
        model.posed_gaussians = slowed(model.posed_gaussians, pose_delay_ms / 1000.0)
    controller = ViewerController(setup.session, motions=(PROJECT,))
    try:
        return SplatPageServer(controller, setup.initial, port=port)
    except BaseException:
        controller.stop()
        raise


def main(argv: list[str] | None = None) -> None:
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from fixtures.browser import Browser, free_port

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("project", type=Path)
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--size", type=int, nargs=2, default=[640, 480])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", type=Path, default=None, help="write the figures as JSON here")
    ap.add_argument("--shots", type=Path, default=None, help="write screenshots here")
    ap.add_argument("--player", type=Path, default=None, help="also measure this `export --format player` page, "
                    "alternating with the viewer's")
    ap.add_argument("--repeats", type=int, default=1, help="rounds of measurements (alternating with --player)")
    ap.add_argument("--budget", choices=("on", "off"), nargs="+", default=["on"],
                    help="the pages' splat budget while moving ('on off': alternating within each round)")
    ap.add_argument("--pose-delay-ms", type=float, default=0.0,
                    help="every uncached posing on the server waits this much more (a slow server; docstring)")
    args = ap.parse_args(argv)
    server = start_viewer(args.project, args.device, free_port(), args.pose_delay_ms)
    figures: dict[str, list[dict]] = {"viewer": [], "player": []}
    rounds = [(r, b == "on") for r in range(max(args.repeats, 1)) for b in args.budget]
    try:
        for _, budget in rounds:
            browser = Browser(*args.size)
            try:
                figures["viewer"].append(asdict(measure(server, browser, args.seconds, tuple(args.size), args.shots,
                                                        budget=budget)))
            finally:
                browser.close()
            if args.player is not None:
                browser = Browser(*args.size)
                try:
                    figures["player"].append(asdict(measure_player(browser, args.player, args.seconds,
                                                                   budget=budget)))
                finally:
                    browser.close()
    finally:
        server.stop()
    text = json.dumps(figures if args.player is not None or len(rounds) > 1 else figures["viewer"][0], indent=1)
    print(text)
    if args.out is not None:
        args.out.write_text(text + "\n")


if __name__ == "__main__":
    main()
