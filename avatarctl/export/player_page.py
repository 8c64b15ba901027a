"""The HTML page of `export --format player` (`export.player.write_player` fills __TITLE__ and __DATA__): a WebGL2
splat renderer written for avatarctl, no libraries, no network. See export/player.py for the data layout.

Drawing (the 3DGS splat equations): per Gaussian, its camera-space centre p and covariance W Sigma W^T; the 2D
covariance J W Sigma W^T J^T + 0.3 I (J the Jacobian of the pinhole projection at p; focal length from the vertical
field of view, pixels); a quad of +-3 sigma along its eigenvectors; alpha = a exp(-d^2 / 2), premultiplied, composited
back to front (a 16-bit counting sort of the view depths on the CPU whenever the view or the frame changes).
Controls: drag to orbit, wheel to zoom, space or the button to play / pause, the slider to scrub.
"""

PAGE = r"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>__TITLE__</title><link rel="icon" href="data:,">
<meta name="viewport" content="width=device-width, initial-scale=1">
<style>
html,body{margin:0;height:100%;background:#f4f4f4;font:13px system-ui,sans-serif;overflow:hidden}
canvas{display:block;width:100%;height:calc(100% - 40px);cursor:grab;touch-action:none}
#bar{height:40px;display:flex;align-items:center;gap:10px;padding:0 12px;background:#fff;border-top:1px solid #ddd}
#seek{flex:1}#status{min-width:170px;color:#444}
</style></head><body>
<canvas id="view"></canvas>
<div id="bar"><button id="play">pause</button><input id="seek" type="range" min="0" max="0" value="0">
<span id="status">loading ...</span></div>
<script id="data" type="application/octet-stream">__DATA__</script>
<script>
"use strict";
const VS = `#version 300 es
precision highp float;
in vec2 corner; in vec3 center; in vec3 covA; in vec3 covB; in vec4 color;
uniform mat3 rot; uniform vec3 eye; uniform vec2 size; uniform float focal;
out vec4 vColor; out vec2 vQ;
void main() {
  vec3 p = rot * (center - eye);
  if (p.z < 0.02) { gl_Position = vec4(0.0, 0.0, 2.0, 1.0); return; }
  mat3 S = mat3(covA.x, covA.y, covA.z, covA.y, covB.x, covB.y, covA.z, covB.y, covB.z);
  mat3 C = rot * S * transpose(rot);
  float iz = 1.0 / p.z;
  vec3 j0 = vec3(focal * iz, 0.0, -focal * p.x * iz * iz);
  vec3 j1 = vec3(0.0, focal * iz, -focal * p.y * iz * iz);
  float a = dot(j0, C * j0) + 0.3, b = dot(j0, C * j1), c = dot(j1, C * j1) + 0.3;
  float mid = 0.5 * (a + c), rad = sqrt(max(0.25 * (a - c) * (a - c) + b * b, 0.0));
  float l1 = mid + rad, l2 = max(mid - rad, 0.1);
  vec2 v1 = abs(b) > 1e-12 ? normalize(vec2(b, l1 - a)) : (a >= c ? vec2(1.0, 0.0) : vec2(0.0, 1.0));
  vec2 v2 = vec2(-v1.y, v1.x);
  vec2 px = vec2(focal * p.x * iz, focal * p.y * iz) + 0.5 * size
          + 3.0 * (corner.x * sqrt(l1) * v1 + corner.y * sqrt(l2) * v2);
  gl_Position = vec4(px.x / size.x * 2.0 - 1.0, 1.0 - px.y / size.y * 2.0, 0.0, 1.0);
  vColor = color; vQ = 3.0 * corner;
}`;
const FS = `#version 300 es
precision highp float;
in vec4 vColor; in vec2 vQ; out vec4 frag;
void main() {
  float alpha = vColor.a * exp(-0.5 * dot(vQ, vQ));
  if (alpha < 1.0 / 255.0) discard;
  frag = vec4(vColor.rgb * alpha, alpha);
}`;

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
  const gl = canvas.getContext("webgl2", {antialias: false, premultipliedAlpha: true});
  if (!gl) fail("this browser has no WebGL2");
  const prog = gl.createProgram();
  for (const [type, src] of [[gl.VERTEX_SHADER, VS], [gl.FRAGMENT_SHADER, FS]]) {
    const sh = gl.createShader(type); gl.shaderSource(sh, src); gl.compileShader(sh);
    if (!gl.getShaderParameter(sh, gl.COMPILE_STATUS)) fail(gl.getShaderInfoLog(sh));
    gl.attachShader(prog, sh);
  }
  gl.linkProgram(prog);
  if (!gl.getProgramParameter(prog, gl.LINK_STATUS)) fail(gl.getProgramInfoLog(prog));
  gl.useProgram(prog);
  const vao = gl.createVertexArray(); gl.bindVertexArray(vao);
  const quad = gl.createBuffer(); gl.bindBuffer(gl.ARRAY_BUFFER, quad);
  gl.bufferData(gl.ARRAY_BUFFER, new Float32Array([-1, -1, 1, -1, -1, 1, 1, 1]), gl.STATIC_DRAW);
  const loc = name => gl.getAttribLocation(prog, name);
  gl.enableVertexAttribArray(loc("corner")); gl.vertexAttribPointer(loc("corner"), 2, gl.FLOAT, false, 0, 0);
  const fbuf = gl.createBuffer(), cbuf = gl.createBuffer();
  gl.bindBuffer(gl.ARRAY_BUFFER, fbuf);
  for (const [name, at] of [["center", 0], ["covA", 3], ["covB", 6]]) {
    gl.enableVertexAttribArray(loc(name)); gl.vertexAttribPointer(loc(name), 3, gl.FLOAT, false, 36, 4 * at);
    gl.vertexAttribDivisor(loc(name), 1);
  }
  gl.bindBuffer(gl.ARRAY_BUFFER, cbuf);
  gl.enableVertexAttribArray(loc("color")); gl.vertexAttribPointer(loc("color"), 4, gl.UNSIGNED_BYTE, true, 0, 0);
  gl.vertexAttribDivisor(loc("color"), 1);
  gl.disable(gl.DEPTH_TEST); gl.enable(gl.BLEND); gl.blendFunc(gl.ONE, gl.ONE_MINUS_SRC_ALPHA);
  const U = name => gl.getUniformLocation(prog, name);

  // orbit camera around the motion's centre, the capture's up
  const up = head.up, norm = v => { const l = Math.hypot(...v) || 1; return v.map(x => x / l); };
  const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
  let e1 = norm(cross(up, Math.abs(up[0]) < 0.9 ? [1, 0, 0] : [0, 1, 0])); const e2 = cross(up, e1);
  const cam = {az: 0, el: 0.15, radius: head.radius, fov: 0.8};
  let frame = 0, playing = true, start = performance.now(), dirty = true, shown = -1;
  const seek = document.getElementById("seek"), status = document.getElementById("status");
  const button = document.getElementById("play");
  seek.max = String(head.frames - 1);
  const setPlaying = p => { playing = p; button.textContent = p ? "pause" : "play";
                            start = performance.now() - frame / head.fps * 1000; };
  button.onclick = () => setPlaying(!playing);
  window.addEventListener("keydown", e => { if (e.code === "Space") { setPlaying(!playing); e.preventDefault(); } });
  seek.oninput = () => { setPlaying(false); frame = Number(seek.value); dirty = true; };
  let drag = null;
  canvas.onpointerdown = e => { drag = [e.clientX, e.clientY]; canvas.setPointerCapture(e.pointerId); };
  canvas.onpointerup = () => { drag = null; };
  canvas.onpointermove = e => {
    if (!drag) return;
    cam.az -= (e.clientX - drag[0]) * 0.008;
    cam.el = Math.max(-1.5, Math.min(1.5, cam.el + (e.clientY - drag[1]) * 0.008));
    drag = [e.clientX, e.clientY]; dirty = true;
  };
  canvas.onwheel = e => { cam.radius *= Math.exp(e.deltaY * 0.001); dirty = true; e.preventDefault(); };

  let order = null, sorted = null, colors = null;
  function draw() {
    const w = canvas.clientWidth, h = canvas.clientHeight;
    if (canvas.width !== w || canvas.height !== h) { canvas.width = w; canvas.height = h; dirty = true; }
    const f = decode(head, frames[frame]), g = f.count, t = head.target;
    const dir = [0, 1, 2].map(k => Math.cos(cam.el) * (Math.cos(cam.az) * e1[k] + Math.sin(cam.az) * e2[k])
                                   + Math.sin(cam.el) * up[k]);
    const eye = t.map((x, k) => x + cam.radius * dir[k]);
    const fwd = dir.map(x => -x), right = norm(cross(fwd, up)), down = cross(fwd, right);
    // depth sort, far to near (16-bit counting sort)
    const depth = new Float32Array(g); let lo = Infinity, hi = -Infinity;
    for (let i = 0; i < g; i++) {
      const d = (f.centers[3 * i] - eye[0]) * fwd[0] + (f.centers[3 * i + 1] - eye[1]) * fwd[1]
              + (f.centers[3 * i + 2] - eye[2]) * fwd[2];
      depth[i] = d; if (d < lo) lo = d; if (d > hi) hi = d;
    }
    const scale = 65535 / Math.max(hi - lo, 1e-9), counts = new Uint32Array(65537), key = new Uint16Array(g);
    for (let i = 0; i < g; i++) { key[i] = 65535 - Math.floor((depth[i] - lo) * scale); counts[key[i] + 1]++; }
    for (let k = 1; k < 65537; k++) counts[k] += counts[k - 1];
    if (!order || order.length !== g) { order = new Uint32Array(g); sorted = new Float32Array(9 * g);
                                        colors = new Uint8Array(4 * g); }
    for (let i = 0; i < g; i++) order[counts[key[i]]++] = i;
    for (let j = 0; j < g; j++) {
      const i = order[j];
      sorted.set(f.centers.subarray(3 * i, 3 * i + 3), 9 * j); sorted.set(f.cov.subarray(6 * i, 6 * i + 6), 9 * j + 3);
      colors.set(f.rgba.subarray(4 * i, 4 * i + 4), 4 * j);
    }
    gl.bindBuffer(gl.ARRAY_BUFFER, fbuf); gl.bufferData(gl.ARRAY_BUFFER, sorted, gl.DYNAMIC_DRAW);
    gl.bindBuffer(gl.ARRAY_BUFFER, cbuf); gl.bufferData(gl.ARRAY_BUFFER, colors, gl.DYNAMIC_DRAW);
    gl.viewport(0, 0, canvas.width, canvas.height);
    gl.clearColor(0.957, 0.957, 0.957, 1); gl.clear(gl.COLOR_BUFFER_BIT);
    gl.uniformMatrix3fv(U("rot"), false, new Float32Array([right[0], down[0], fwd[0], right[1], down[1], fwd[1],
                                                            right[2], down[2], fwd[2]]));
    gl.uniform3fv(U("eye"), eye); gl.uniform2f(U("size"), canvas.width, canvas.height);
    gl.uniform1f(U("focal"), 0.5 * canvas.height / Math.tan(cam.fov / 2));
    gl.drawArraysInstanced(gl.TRIANGLE_STRIP, 0, 4, g);
  }
  function tick(now) {
    if (playing && head.frames > 1) {
      const next = Math.floor(Math.max(now - start, 0) / 1000 * head.fps) % head.frames;
      if (next !== frame) { frame = next; dirty = true; }
    }
    if (dirty || frame !== shown) {
      draw(); dirty = false; shown = frame; seek.value = String(frame);
      status.textContent = `${head.labels[frame] || "frame " + frame} · ${frame + 1}/${head.frames} · ${head.fps} fps`;
    }
    requestAnimationFrame(tick);
  }
  window.__player = {head, get frame() { return frame; }, setPlaying};
  requestAnimationFrame(tick);
}
main();
</script></body></html>
"""
