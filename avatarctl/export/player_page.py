"""The HTML page of `export --format player` (`export.player.write_player` fills __TITLE__ and __DATA__): a player
around the WebGL2 splat renderer of `splat.webgl` (ours: no libraries, no network). See export/player.py for the data
layout; the page unpacks it, rebuilds each covariance R S^2 R^T and hands a frame's Gaussians to the renderer.
Controls: drag to orbit, wheel to zoom, space or the button to play / pause, the slider to scrub, "fast preview while
moving" (the renderer's splat budget while the view moves or plays, on by default; the status shows it).
"""

from avatarctl.splat.webgl import RENDERER_JS

MOVING_SCALE = 1.0  # pixels per side drawn while the camera moves (splat.webgl: SplatRenderer.movingScale)


PAGE = r"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>__TITLE__</title><link rel="icon" href="data:,">
<meta name="viewport" content="width=device-width, initial-scale=1">
<style>
html,body{margin:0;height:100%;background:#f4f4f4;font:13px system-ui,sans-serif;overflow:hidden}
canvas{display:block;width:100%;height:calc(100% - 40px);cursor:grab}
#bar{height:40px;display:flex;align-items:center;gap:10px;padding:0 12px;background:#fff;border-top:1px solid #ddd}
#bar{overflow:hidden}#bar label{white-space:nowrap}
#seek{flex:1;min-width:80px}#status{color:#444;white-space:nowrap;overflow:hidden;text-overflow:ellipsis}
</style></head><body>
<canvas id="view"></canvas>
<div id="bar"><button id="play">pause</button><input id="seek" type="range" min="0" max="0" value="0">
<label title="while the camera moves or the motion plays, draw a sample of the Gaussians"><input id="lod"
 type="checkbox" checked> fast preview while moving</label><span id="status">loading ...</span></div>
<script id="data" type="application/octet-stream">__DATA__</script>
<script>
"use strict";
__RENDERER__
function fail(msg) { document.getElementById("status").textContent = msg; throw new Error(msg); }

async function unpack() {
  const text = document.getElementById("data").textContent.trim();
  const raw = Uint8Array.from(atob(text), ch => ch.charCodeAt(0));
  const stream = new Blob([raw]).stream().pipeThrough(new DecompressionStream("gzip"));
  const buf = await new Response(stream).arrayBuffer();
  const n = new DataView(buf).getUint32(0, true);
  const head = JSON.parse(new TextDecoder().decode(new Uint8Array(buf, 4, n)));
  const frames = []; let off = 4 + n;
  for (const g of head.counts) {
    const f = {count: g, pos: new Uint8Array(buf, off, 6 * g)}; off += 6 * g;
    f.rot = new Int8Array(buf, off, 4 * g); off += 4 * g;
    f.scale = new Uint8Array(buf, off, 3 * g); off += 3 * g;
    f.rgba = new Uint8Array(buf, off, 4 * g); off += 4 * g;
    frames.push(f);
  }
  return {head, frames};
}

function decode(head, f) {  // -> centres [g*3], covariance upper triangles [g*6], rgba [g*4]
  if (f.centers) return f;
  const g = f.count, lo = head.lo, hi = head.hi, ls = head.log_scale;
  const pos = new Uint16Array(f.pos.buffer.slice(f.pos.byteOffset, f.pos.byteOffset + 6 * g));
  const centers = new Float32Array(3 * g), cov = new Float32Array(6 * g);
  for (let i = 0; i < g; i++) {
    for (let k = 0; k < 3; k++) centers[3 * i + k] = lo[k] + (hi[k] - lo[k]) * pos[3 * i + k] / 65535;
    let w = f.rot[4 * i], x = f.rot[4 * i + 1], y = f.rot[4 * i + 2], z = f.rot[4 * i + 3];
    const nq = Math.hypot(w, x, y, z) || 1; w /= nq; x /= nq; y /= nq; z /= nq;
    const R = [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
               2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
               2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)];
    const s2 = [0, 1, 2].map(k => Math.exp(2 * (ls[0] + (ls[1] - ls[0]) * f.scale[3 * i + k] / 255)));
    const c = (r, q) => R[3 * r] * R[3 * q] * s2[0] + R[3 * r + 1] * R[3 * q + 1] * s2[1] + R[3 * r + 2] * R[3 * q + 2] * s2[2];
    cov.set([c(0, 0), c(0, 1), c(0, 2), c(1, 1), c(1, 2), c(2, 2)], 6 * i);
  }
  f.centers = centers; f.cov = cov;
  return f;
}

async function main() {
  const {head, frames} = await unpack();
  const canvas = document.getElementById("view");
  let renderer;
  try { renderer = new SplatRenderer(canvas, [0.957, 0.957, 0.957], {lowPass: head.low_pass}); }
  catch (e) { fail(e.message); }
  renderer.movingScale = MOVING_SCALE;
  // orbit camera around the motion's centre, the capture's up
  const cam = {target: head.target, up: head.up, az: 0, el: 0.15, radius: head.radius, fov: 0.8};
  let label = "", frame = 0, playing = true, start = performance.now(), dirty = true, shown = -1;
  const seek = document.getElementById("seek"), status = document.getElementById("status");
  const button = document.getElementById("play");
  seek.max = String(head.frames - 1);
  const lod = document.getElementById("lod");
  lod.onchange = () => { renderer.lod.enabled = lod.checked; dirty = true; };
  const setPlaying = p => { playing = p; button.textContent = p ? "pause" : "play";
                            renderer.animating = p && head.frames > 1;
                            start = performance.now() - frame / head.fps * 1000; };
  button.onclick = () => setPlaying(!playing);
  window.addEventListener("keydown", e => { if (e.code === "Space") { setPlaying(!playing); e.preventDefault(); } });
  seek.oninput = () => { setPlaying(false); frame = Number(seek.value); dirty = true; };
  OrbitControls(canvas, cam, () => { renderer.moved(); dirty = true; });

  function tick(now) {
    if (playing && head.frames > 1) {
      const next = Math.floor(Math.max(now - start, 0) / 1000 * head.fps) % head.frames;
      if (next !== frame) { frame = next; dirty = true; }
    }
    if (frame !== shown) {
      const f = decode(head, frames[frame]);
      renderer.setSplats(f.centers, f.cov, f.rgba);
      shown = frame; seek.value = String(frame); dirty = true;
      label = `${head.labels[frame] || "frame " + frame} · ${frame + 1}/${head.frames} · ${head.fps} fps`;
    }
    if (dirty || renderer.settling) {
      renderer.draw(orbitView(cam)); dirty = false;
      const text = `${label} · ${renderer.budgetText()}`;
      if (status.textContent !== text) status.textContent = text;
    }
    requestAnimationFrame(tick);
  }
  renderer.animating = head.frames > 1;
  window.__player = {head, get frame() { return frame; }, setPlaying, renderer};
  requestAnimationFrame(tick);
}
main();
</script></body></html>
""".replace("__RENDERER__", RENDERER_JS).replace("MOVING_SCALE", repr(MOVING_SCALE))
