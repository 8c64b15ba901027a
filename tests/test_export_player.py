"""`export --format splat,player` of a Gaussian-field avatar: per-frame 3DGS .ply files (read by a third-party splat
tool, PlayCanvas's splat-transform from npm, installed into a cache at test time) and the self-contained HTML
player (played in headless Chromium: no console error, three moments differ)."""

from __future__ import annotations

import json
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest


@pytest.fixture(scope="module")
def exported(toy_gaussian_project):
    from avatarctl.stages import export
    from avatarctl.stages.export import ExportConfig

    res = export.run(toy_gaussian_project, ExportConfig(name="splats", formats=("splat", "player"), device="cpu"))
    return res


def test_splat_and_player_files(exported, toy_gaussian_project):
    from avatarctl.export.player import BYTES_PER_GAUSSIAN

    plys = sorted(f for f in exported.splats if f.startswith("splats/"))
    assert len(plys) == 4 and "player.html" in exported.splats, "the toy's 4 frames (player default: up to 30)"
    assert not exported.meshes and exported.avatar is None, "no mesh products with splat formats alone"
    head = (exported.out_dir / plys[0]).read_bytes()[:2000].decode("latin-1")
    assert head.startswith("ply\nformat binary_little_endian 1.0\ncomment avatarctl low_pass 0.1\nelement vertex 768\n")
    html = (exported.out_dir / "player.html").read_text()
    assert "http://" not in html and "https://" not in html, "self-contained: nothing fetched"
    assert exported.splats["player.html"] < 4 * 768 * BYTES_PER_GAUSSIAN * 1.4 + 30_000
    record = json.loads((exported.out_dir / "export.json").read_text())
    assert record["splats"] == exported.splats


def test_gaussian_formats_refuse_a_ray_marched_avatar(toy_fitted_project):
    from avatarctl.errors import InputError
    from avatarctl.stages import export
    from avatarctl.stages.export import ExportConfig

    with pytest.raises(InputError, match="needs a Gaussian-field avatar"):
        export.run(toy_fitted_project, ExportConfig(name="nope", formats=("player",), device="cpu"))


def _npm_package(cache: Path, spec: str, bin_name: str) -> Path:
    """`bin_name` of the npm package `spec`, installed into `cache` once; skips when node / npm / the registry
    are not reachable."""
    exe = cache / "node_modules" / ".bin" / bin_name
    if exe.exists():
        return exe
    if shutil.which("npm") is None or shutil.which("node") is None:
        pytest.skip("no node / npm on this machine")
    cache.mkdir(parents=True, exist_ok=True)
    try:
        proc = subprocess.run(["npm", "install", "--no-audit", "--no-fund", "--prefix", str(cache), spec],
                              capture_output=True, text=True, timeout=300)
    except subprocess.TimeoutExpired:
        pytest.skip(f"npm install {spec} timed out (registry unreachable?)")
    if proc.returncode != 0 or not exe.exists():
        pytest.skip(f"npm install {spec} failed (registry unreachable?): {proc.stderr.strip()[-200:]}")
    return exe


def test_splat_ply_opens_in_playcanvas_splat_transform(exported, tmp_path):
    """A third-party reader: splat-transform (PlayCanvas, npm) reads our .ply and writes it back as CSV; the
    centres, opacities and colours it read are ours."""
    import os

    cache = Path(os.environ.get("AVATARCTL_NPM_CACHE", Path.home() / ".cache" / "avatarctl-npm"))
    exe = _npm_package(cache, "@playcanvas/splat-transform@3", "splat-transform")
    ply = exported.out_dir / sorted(f for f in exported.splats if f.startswith("splats/"))[0]
    out = tmp_path / "read.csv"
    proc = subprocess.run([str(exe), str(ply), str(out)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0 and out.is_file(), proc.stdout[-500:] + proc.stderr[-500:]
    lines = out.read_text().splitlines()
    names = lines[0].split(",")
    table = np.array([[float(x) for x in s.split(",")] for s in lines[1:]])
    assert table.shape[0] == 768
    trimesh = pytest.importorskip("trimesh")
    ours = trimesh.load(ply).metadata["_ply_raw"]["vertex"]["data"]
    for name in ("x", "y", "z", "opacity", "f_dc_0", "scale_0", "rot_0"):
        assert np.allclose(table[:, names.index(name)], ours[name], atol=1e-5), name


@pytest.mark.browser
def test_player_plays_in_headless_chromium(exported, tmp_path):
    from fixtures.browser import Browser, find_chromium

    if find_chromium() is None:
        pytest.skip("no chromium / chrome on this machine")
    pytest.importorskip("websockets")  # the DevTools client (installed with the `view` extra, not with `test`)
    import cv2

    browser = Browser(480, 400)
    try:
        browser.call("Runtime.enable")
        browser.call("Log.enable")
        browser.open((exported.out_dir / "player.html").as_uri())
        shots, shown, deadline = [], [], time.monotonic() + 60
        while time.monotonic() < deadline and len(shots) < 3:  # a screenshot whenever the playing frame moved on
            frame = browser.call("Runtime.evaluate", expression="window.__player ? window.__player.frame : -1",
                                 returnByValue=True)["result"].get("value")
            if frame is not None and frame >= 0 and frame not in shown[-1:]:
                shot = browser.screenshot()  # the page draws on the next animation frame: on a busy machine that can
                t_draw = time.monotonic() + 5  # lag, so wait (at most 5 s) until the canvas shows something new
                while shots and time.monotonic() < t_draw and np.abs(
                        shot[:-40].astype(float) - shots[-1][:-40].astype(float)).mean() <= 0.05:
                    time.sleep(0.05)
                    shot = browser.screenshot()
                shots.append(shot)
                shown.append(frame)
            else:
                time.sleep(0.01)
        errors = [m for m in browser.events if m.get("method") in ("Runtime.exceptionThrown",)
                  or (m.get("method") == "Runtime.consoleAPICalled" and m["params"].get("type") == "error")
                  or (m.get("method") == "Log.entryAdded" and m["params"]["entry"].get("level") == "error")]
    finally:
        browser.close()
    assert len(shots) == 3, "the player never started"
    for k, s in enumerate(shots):
        cv2.imwrite(str(tmp_path / f"player_{k}.png"), s[..., ::-1])
    assert not errors, errors
    canvas = [s[:-40].astype(float) for s in shots]
    assert canvas[0].std() > 2, "something is drawn"
    assert np.abs(canvas[0] - canvas[1]).mean() > 0.05 and np.abs(canvas[1] - canvas[2]).mean() > 0.05, \
        "three moments of the motion differ"


@pytest.mark.browser
def test_player_draws_a_splat_budget_while_playing_and_all_at_rest(exported):
    """The player shares the renderer's splat budget: playing on a (mimicked) slow machine draws fewer Gaussians,
    paused at rest all of them, the same picture as with "fast preview while moving" off."""
    from fixtures.browser import Browser, find_chromium

    if find_chromium() is None:
        pytest.skip("no chromium / chrome on this machine")
    pytest.importorskip("websockets")
    from benchmarks.viewer_page import canvas_rect, evaluate, wait_for

    browser = Browser(480, 400)

    def wait(expr: str):
        wait_for(browser, expr)

    try:
        browser.open((exported.out_dir / "player.html").as_uri())
        wait("window.__player && window.__splatStats.gaussians > 0")
        evaluate(browser, "window.__player.setPlaying(false); const r = window.__player.renderer;"
                          " r.lod.minSplats = 64; r.lod.measureScale = 1e4; window.__splatStats.drawn = -1; r.moved()")
        wait("window.__splatStats.drawn === window.__splatStats.gaussians && window.__splatStats.timed > 0")
        n = evaluate(browser, "window.__splatStats.gaussians")
        evaluate(browser, "window.__player.setPlaying(true)")
        wait("window.__splatStats.moving === 64 && window.__splatStats.drawn === 64")
        assert "preview 64 / " in evaluate(browser, "document.getElementById('status').textContent")
        evaluate(browser, "window.__player.setPlaying(false)")
        wait(f"window.__splatStats.drawn === {n} && !window.__player.renderer.moving")
        time.sleep(0.3)
        x, y, w, h = canvas_rect(browser)
        rest = browser.screenshot()[y:y + h, x:x + w].astype(float)
        evaluate(browser, "window.__splatStats.drawn = -1; document.getElementById('lod').click()")
        wait(f"window.__splatStats.drawn === {n}")
        time.sleep(0.3)
        without = browser.screenshot()[y:y + h, x:x + w].astype(float)
    finally:
        browser.close()
    assert rest.std() > 2, "something is drawn"
    assert np.abs(rest - without).max() <= 2, "at rest the budget draws the no-budget picture"


def test_the_low_pass_is_one_value_from_the_model_to_every_renderer(tmp_path, monkeypatch):
    """Issue 49: the screen-space low-pass an avatar was trained with (`model.gaussians.low_pass`, here 0.17 px^2, neither
    the default 0.1 nor 3DGS's 0.3) is the one its training rasterizer, `render`, the `.ply` export, the player page
    and the viewer page use (the page: the next test); the browser renderer holds no value of its own."""
    import base64
    import gzip
    import re

    import avatarctl.splat as splat
    from fixtures.toy_capture import make_toy_capture

    from avatarctl.splat.webgl import RENDERER_JS
    from avatarctl.stages import export, fit, ingest
    from avatarctl.stages.export import ExportConfig
    from avatarctl.stages.fit import FitRequest
    from avatarctl.stages.ingest import IngestConfig
    from avatarctl.stages.view import ViewConfig, prepare

    value = 0.17
    used: list[float] = []
    real = splat.rasterization  # every rasterization the model asks for
    monkeypatch.setattr(splat, "rasterization", lambda *a, **k: (used.append(k["low_pass"]), real(*a, **k))[1])
    cap, proj = make_toy_capture(tmp_path / "cap"), tmp_path / "proj"
    ingest.run(proj, IngestConfig(capture=cap, project=proj, contact_sheet=False))
    fit.run(proj, FitRequest(preset="micro", iters=2, device="cpu", overrides=(
        "model.field=gaussians", "model.gaussians.per_node=8", f"model.gaussians.low_pass={value}", "val_every=0")),
        handle_sigint=False)
    assert used and set(used) == {value}, "training (and its validation) rasterize with the model's low-pass"
    res = export.run(proj, ExportConfig(name="splats", formats=("splat", "player"), device="cpu"))
    ply = res.out_dir / sorted(f for f in res.splats if f.startswith("splats/"))[0]
    head = ply.read_bytes().split(b"end_header")[0].decode("ascii")
    assert f"comment avatarctl low_pass {value!r}" in head
    html = (res.out_dir / "player.html").read_text()
    block = gzip.decompress(base64.b64decode(re.search(r'<script id="data" type="application/octet-stream">([^<]+)</script>', html).group(1)))
    header = json.loads(block[4:4 + int.from_bytes(block[:4], "little")])
    assert header["low_pass"] == value and "{lowPass: head.low_pass}" in html
    shader = RENDERER_JS.split("const SPLAT_FS")[0]
    assert "+ lowPass" in shader and not re.search(r"\+ ?0\.3\b", shader), "no hard-coded low-pass in the browser"
    setup = prepare(proj, ViewConfig(device="cpu"))  # what the viewer serves
    assert setup.session.model.cfg.gaussians.low_pass == value


def test_the_viewer_page_draws_with_the_served_avatars_low_pass(toy_gaussian_project):
    """The `avatarctl view` page of a Gaussian avatar hands the browser renderer that avatar's low-pass."""
    pytest.importorskip("websockets", reason="the viewer's extra: pip install 'avatarctl[view]'")
    from avatarctl.stages.view import ViewConfig, prepare
    from avatarctl.viewer.controller import ViewerController
    from avatarctl.viewer.splat_server import SplatPageServer

    setup = prepare(toy_gaussian_project, ViewConfig(device="cpu"))
    value = setup.session.model.cfg.gaussians.low_pass
    assert value != 0.3  # the old hard-coded value, so the check below can fail
    controller = ViewerController(setup.session)
    server = SplatPageServer(controller, setup.initial, port=0)
    try:
        assert f"{{lowPass: {value}}}" in server.page.decode()
    finally:
        server.stop()
        controller.stop()
