"""The page `avatarctl view` serves for a Gaussian-field avatar (`viewer.splat_server` fills it): the WebGL2 splat
renderer of `splat.webgl` (shared with the export player) and the viewer's panel, talking to the viewer process over
one websocket at `/ws`.

Messages from the server: text = the panel's state (`controller.ViewState` as JSON: labels, frame, playing, fps,
latent, motions, status, ...); binary = `uint32 n` + an n-byte JSON header + payload, the header's "kind" saying
what: "splats" (a posed frame, `splats.encode_splats`; the page draws it at its next animation frame and answers
{"cmd": "drawn", "seq"}, so the server never sends a frame before the previous one is drawn) or "image" (a PNG of
the exact server render, shown over the canvas until the camera moves or a frame other than its own arrives).
Messages from the page: {"cmd": ...} with "frame", "play", "fps", "latent", "resolution", "camera_path",
"motion" (name, add), "render" (view, aspect), "video", "drawn" (seq).

`window.__viewer` exposes what was drawn (`shown`: the header of the frame on the canvas, `draws`, the `renderer`) for
tests and the benchmark; `window.__splatStats` the renderer's splat budget (`splat.webgl`). The "fast preview while
moving" checkbox switches the budget (`SplatRenderer.lod.enabled`); the status line shows it.
"""

import json

from avatarctl.splat.webgl import RENDERER_JS

MOVING_SCALE = 1.0  # pixels per side drawn while the camera moves (splat.webgl: SplatRenderer.movingScale)

PAGE = r"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>avatarctl view</title><link rel="icon" href="data:,">
<meta name="viewport" content="width=device-width, initial-scale=1">
<style>
html,body{margin:0;height:100%;font:13px system-ui,sans-serif;overflow:hidden;background:#f4f4f4}
#stage{position:absolute;left:0;top:0;bottom:0;right:260px}
#view,#exact{position:absolute;left:0;top:0;width:100%;height:100%;display:block}
#view{cursor:grab}#exact{display:none;pointer-events:none}
#panel{position:absolute;right:0;top:0;bottom:0;width:260px;box-sizing:border-box;padding:8px;overflow-x:hidden;overflow-y:auto;background:#fff;
border-left:1px solid #ddd;display:flex;flex-direction:column;gap:7px}
#panel label{display:flex;align-items:center;justify-content:space-between;gap:6px}
#panel select,#panel input[type=text]{width:150px}#panel input[type=number]{width:70px}
#frame{width:100%}#status{white-space:pre-line;color:#333;background:#f4f4f4;padding:6px;border-radius:4px}
#label{color:#444}
</style></head><body>
<div id="stage"><canvas id="view"></canvas><img id="exact" alt="server render"></div>
<div id="panel">
<div id="status">connecting ...</div>
<label>motion <select id="motion"></select></label>
<label>motion file <input id="file" type="text" placeholder="path on the server"></label>
<button id="load">load motion</button>
<div id="label"></div>
<input id="frame" type="range" min="0" max="0" step="1" value="0">
<label><span><input id="play" type="checkbox"> play</span> <span>fps <input id="fps" type="number" min="0.5"
 max="240" step="0.5"></span></label>
<label>latent <select id="latent"><option>auto</option><option>mean</option><option>zero</option>
<option>sample</option></select></label>
<label>resolution <input id="resolution" type="number" min="16" max="2048" step="32"></label>
<button id="render" title="the exact image of this view (the renderer of `render` / `eval`)">render</button>
<label>video camera <select id="camera_path"><option>held-out view</option><option>orbit</option></select></label>
<button id="video" title="run `avatarctl render` for this motion, latent and camera path">save video</button>
<label title="while the camera moves or the motion plays, draw a sample of the Gaussians (as many as this
 machine draws in about 10 ms); all of them at rest"><span><input id="lod" type="checkbox" checked> fast preview while
 moving</span></label>
<div style="color:#777">drag: orbit · wheel: zoom · space: play</div>
</div>
<script>
"use strict";
__RENDERER__
const $ = id => document.getElementById(id);
const canvas = $("view"), exact = $("exact"), statusEl = $("status"), slider = $("frame");
const renderer = new SplatRenderer(canvas, __BACKGROUND__, {lowPass: __LOW_PASS__});
renderer.movingScale = MOVING_SCALE;
const init = __INITIAL__;
const vdot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const cam = (() => {  // the orbit camera through the initial position, looking at the subject
  const up = vnorm(init.up), [e1, e2] = orbitBasis(up);
  const d = init.position.map((x, k) => x - init.look_at[k]), radius = Math.hypot(...d) || 1;
  const dir = d.map(x => x / radius), el = Math.asin(Math.max(-1, Math.min(1, vdot(dir, up))));
  return {target: init.look_at, up, az: Math.atan2(vdot(dir, e2), vdot(dir, e1)),
          el: Math.max(-1.5, Math.min(1.5, el)), radius, fov: init.fov};
})();
const HALF = (() => {  // float16 bits -> float32
  const t = new Float32Array(65536);
  for (let h = 0; h < 65536; h++) {
    const s = h & 0x8000 ? -1 : 1, e = (h >> 10) & 31, m = h & 1023;
    t[h] = s * (e === 0 ? m * 2 ** -24 : e === 31 ? (m ? NaN : Infinity) : (1 + m / 1024) * 2 ** (e - 15));
  }
  return t;
})();
let lodText = "";
let ws = null, state = null, exactKey = null, pending = null, shown = null, acked = -1, dirty = true, sliding = false, draws = 0;

function send(msg) { if (ws && ws.readyState === WebSocket.OPEN) ws.send(JSON.stringify(msg)); }

function decodeSplats(head, buf, off) {  // splats.encode_splats -> centres [g*3], covariances [g*6], rgba [g*4]
  const g = head.count, q = new Uint16Array(buf, off, 3 * g), h = new Uint16Array(buf, off + 6 * g, 6 * g);
  const rgba = new Uint8Array(buf, off + 18 * g, 4 * g);
  const centers = new Float32Array(3 * g), cov = new Float32Array(6 * g), lo = head.lo;
  const step = [0, 1, 2].map(k => (head.hi[k] - lo[k]) / 65535), inv = 1 / head.cov_scale;
  for (let i = 0; i < 3 * g; i += 3) {
    centers[i] = lo[0] + step[0] * q[i]; centers[i + 1] = lo[1] + step[1] * q[i + 1];
    centers[i + 2] = lo[2] + step[2] * q[i + 2];
  }
  for (let j = 0; j < 6 * g; j++) cov[j] = HALF[h[j]] * inv;
  return {centers, cov, rgba};
}

function hideExact() { if (exact.style.display !== "none") { exact.style.display = "none"; dirty = true; } }

function onBinary(buf) {
  const n = new DataView(buf).getUint32(0, true), off = 4 + n;
  const head = JSON.parse(new TextDecoder().decode(new Uint8Array(buf, 4, n)));
  if (head.kind === "splats") pending = {head, buf, off};  // drawn at the next animation frame: the newest wins
  else if (head.kind === "image") {
    if (exact.src) URL.revokeObjectURL(exact.src);
    exact.src = URL.createObjectURL(new Blob([new Uint8Array(buf, off)], {type: "image/png"}));
    exact.style.display = "block"; $("render").disabled = false; exactKey = head;
  } else if (head.kind === "error") $("render").disabled = false;
}

function setOptions(select, names) {
  const now = [...select.options].map(o => o.value);
  if (now.length === names.length && now.every((x, i) => x === names[i])) return;
  select.replaceChildren(...names.map(x => new Option(x, x)));
}

function onState(s) {
  state = s;
  setOptions($("motion"), s.motions); $("motion").value = s.motion; $("motion").disabled = s.motions.length < 2;
  $("file").disabled = $("load").disabled = !s.can_load;
  slider.max = String(Math.max(s.labels.length - 1, 0)); slider.disabled = s.labels.length < 2;
  if (!sliding) slider.value = String(s.frame);
  $("label").textContent = `${s.labels[s.frame]} · ${s.frame + 1}/${s.labels.length}`;
  $("play").checked = s.playing;
  if (document.activeElement !== $("fps")) $("fps").value = String(s.fps);
  if (document.activeElement !== $("resolution")) $("resolution").value = String(s.resolution);
  $("latent").value = s.latent; $("camera_path").value = s.camera_path; $("video").disabled = !s.can_video;
  renderer.animating = s.playing;
  showStatus();
}

function showStatus() {  // the server's status line and the splat budget (splat.webgl: budgetText)
  lodText = renderer.budgetText();
  statusEl.textContent = state ? (lodText ? `${state.status}\n${lodText}` : state.status) : "connecting ...";
}

function connect() {
  ws = new WebSocket(`${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/ws`);
  ws.binaryType = "arraybuffer";
  ws.onmessage = e => (typeof e.data === "string" ? onState(JSON.parse(e.data)) : onBinary(e.data));
  ws.onclose = () => { statusEl.textContent = "disconnected: the viewer stopped (start `avatarctl view` again)"; };
}

slider.addEventListener("pointerdown", () => { sliding = true; });
window.addEventListener("pointerup", () => { sliding = false; });
slider.oninput = () => send({cmd: "frame", value: Number(slider.value)});
$("play").onchange = () => send({cmd: "play", value: $("play").checked});
$("fps").onchange = () => send({cmd: "fps", value: Number($("fps").value)});
$("latent").onchange = () => send({cmd: "latent", value: $("latent").value});
$("resolution").onchange = () => send({cmd: "resolution", value: Number($("resolution").value)});
$("camera_path").onchange = () => send({cmd: "camera_path", value: $("camera_path").value});
$("motion").onchange = () => send({cmd: "motion", name: $("motion").value, add: false});
$("load").onclick = () => send({cmd: "motion", name: $("file").value, add: true});
$("video").onclick = () => send({cmd: "video"});
$("lod").onchange = () => { renderer.lod.enabled = $("lod").checked; dirty = true; };
$("render").onclick = () => {
  $("render").disabled = true;
  send({cmd: "render", view: orbitView(cam), aspect: canvas.clientWidth / Math.max(canvas.clientHeight, 1)});
};
window.addEventListener("keydown", e => {
  if (e.code === "Space" && e.target.tagName !== "INPUT") { send({cmd: "play", value: !(state && state.playing)});
                                                             e.preventDefault(); }
});
OrbitControls(canvas, cam, () => { renderer.moved(); hideExact(); dirty = true; });
window.addEventListener("resize", () => { dirty = true; });

function tick() {
  if (pending) {
    const {head, buf, off} = pending, f = decodeSplats(head, buf, off);
    pending = null;
    const k = exactKey;
    if (k && (k.frame !== head.frame || k.generation !== head.generation || k.latent !== head.latent)) hideExact();
    renderer.setSplats(f.centers, f.cov, f.rgba);
    shown = head; dirty = true;
  }
  if (dirty || renderer.settling) {
    renderer.draw(orbitView(cam)); dirty = false; draws++;
    if (renderer.budgetText() !== lodText) showStatus();
    if (shown && shown.seq !== acked) { acked = shown.seq; send({cmd: "drawn", seq: shown.seq}); }
  }
  requestAnimationFrame(tick);
}
window.__viewer = {get shown() { return shown; }, get state() { return state; }, get draws() { return draws; },
                   get exactShown() { return exact.style.display !== "none"; }, renderer};
connect();
requestAnimationFrame(tick);
</script></body></html>
""".replace("__RENDERER__", RENDERER_JS).replace("MOVING_SCALE", repr(MOVING_SCALE))


def page_html(background: tuple[float, float, float], position: tuple[float, float, float],
              look_at: tuple[float, float, float], up: tuple[float, float, float], fov_y: float,
              low_pass: float) -> str:
    """The page for one avatar: its background colour (RGB in [0, 1]), where the orbit camera starts (world,
    metres; `fov_y` the vertical field of view, radians) and its splats' low-pass (px^2, `model.gaussians.low_pass`)."""
    initial = {"position": list(position), "look_at": list(look_at), "up": list(up), "fov": float(fov_y)}
    return (PAGE.replace("__BACKGROUND__", json.dumps([float(c) for c in background]))
            .replace("__LOW_PASS__", json.dumps(float(low_pass)))
            .replace("__INITIAL__", json.dumps(initial)))
