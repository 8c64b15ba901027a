"""The browser twin of the rasterizer: a WebGL2 splat renderer in JavaScript, written for avatarctl (no libraries,
no network), shared by every page that draws Gaussians (`export --format player`, the live page of `avatarctl view`).

`RENDERER_JS` defines, in the page's scope:
- `SplatRenderer(canvas, background, {lowPass, lod})`: `lowPass` (px^2, required) is the avatar's
  `model.gaussians.low_pass`, the value it was trained and is rendered with (one value from the model to every
  renderer: tests/test_splat.py); `setSplats(centers, cov, rgba)` (Float32Array [G*3] metres,
  Float32Array [G*6] upper triangles of the world covariances (xx, xy, xz, yy, yz, zz) in metres^2, Uint8Array [G*4]
  RGBA), then `draw(view)` with `view = {eye, right, down, fwd, fov}` (world vectors: the OpenCV camera axes x right,
  y down, z forward; `fov` the vertical field of view, radians). `moved()` when the camera moves: for 0.25 s after it
  the image is drawn at `movingScale` of the canvas' pixels per side (then upscaled by the browser), and `settling` is
  true whenever a redraw is due (after `moved()`, and once the full image is due at rest: the page then calls `draw`
  again).
- the splat budget while the view moves (level of detail, `renderer.lod`, on unless `new SplatRenderer(canvas,
  background, {lod: {enabled: false}})`): while the camera moves (`moved()`), a new frame arrives (`setSplats`) or the
  page animates (`renderer.animating = true`, a playing motion), only `budget` of the G Gaussians are drawn: a uniform
  sample (the prefix of a fixed pseudo-random permutation, the same Gaussians from one draw to the next), each one's
  2D covariance grown by (G / budget)^0.6 so that the sample still covers the surface (the back-to-front sort runs
  over the sample only). Measured on synth small (docs/export_view.md): an importance ranking (opacity x
  det(Sigma)^(1/3), a projected-area proxy) keeps the large Gaussians (skirt, the body's inside) and drops the small
  ones of the surface, so the preview shows through the torso (21-23 dB PSNR against the full image at 2,000-3,000 of
  24k); the grown uniform sample gives 27-29 dB. 0.25 s after the last change, and not animating, all of them
  (`settling` asks for that redraw; the image at rest is the no-budget image). The budget adapts to the machine: full
  draws are timed to completion (a 1-pixel `readPixels`, a sync point that waits for the rasterizer; each full draw at
  rest, and one in 8 while all are drawn), and budget = clamp(lod.splatMs / (measured ms per drawn splat),
  min(lod.minSplats, G), G): the splats of a moving frame take about `lod.splatMs` = 10 ms to draw, so that with the
  rest of a frame (the page's sort, the browser's compositing: some 40 ms of CPU a frame in headless Chromium's
  SwiftShader, docs/export_view.md) it runs near 30 frames/s; a hardware GPU keeps budget = G. `lod.measureScale`
  multiplies the measured times (tests mimic a slow machine with it); `lod.holdPreview` keeps the budget at rest
  (screenshots of the preview). `stats` (also `window.__splatStats`): Gaussians, budget, splats of the last draw, of
  the last moving draw and of the last draw at rest, the estimate in us per splat; `budgetText()` a line for the
  page's status.
- `OrbitControls(canvas, camera, onChange)`: drag to orbit about `camera.target` around `camera.up`, wheel to zoom;
  `orbitView(camera)` -> the `view` of an orbit camera {target, up, az, el, radius, fov}.

Drawing (the 3DGS splat equations, as `splat.project` / `splat.rasterizer`): per Gaussian its camera-space centre p
and covariance W Sigma W^T; the 2D covariance J W Sigma W^T J^T + lowPass I (J the Jacobian of the pinhole projection at
p; focal length from the vertical field of view, pixels); a quad along its eigenvectors out to the radius where
a exp(-d^2 / 2) falls under 1/255 (at most 3 sigma); premultiplied alpha composited back to front (a 16-bit counting
sort of the view depths on the CPU whenever the view or the Gaussians change; only the order is uploaded).

Why no instancing: software WebGL (SwiftShader, the CPU floor the viewer is measured on) pays about 20-30 us per
instance of an instanced draw, so 24k Gaussians cost 0.45-0.75 s a frame (viser's splat node and our first player);
here one non-instanced draw of 4 vertices and 6 indices per Gaussian (`gl_VertexID` picks the Gaussian, whose data
the vertex shader fetches from float textures by its sorted rank) costs a few microseconds per Gaussian.
"""

RENDERER_JS = r"""
const SPLAT_VS = `#version 300 es
precision highp float; precision highp int; precision highp usampler2D; precision highp sampler2D;
uniform sampler2D data; uniform usampler2D order; uniform sampler2D colors;
uniform mat3 rot; uniform vec3 eye; uniform vec2 size; uniform float focal; uniform float grow;
uniform float lowPass;
out vec4 vColor; out vec2 vQ;
const vec2 CORNERS[4] = vec2[4](vec2(-1.0, -1.0), vec2(1.0, -1.0), vec2(-1.0, 1.0), vec2(1.0, 1.0));
ivec2 at(int k) { return ivec2(k & 4095, k >> 12); }
void main() {
  gl_Position = vec4(0.0, 0.0, 2.0, 1.0);
  int i = int(texelFetch(order, at(gl_VertexID >> 2), 0).r);
  vec2 corner = CORNERS[gl_VertexID & 3];
  vec4 d0 = texelFetch(data, at(3 * i), 0), d1 = texelFetch(data, at(3 * i + 1), 0);
  vec3 p = rot * (d0.xyz - eye);
  if (p.z < 0.02) return;
  vec4 d2 = texelFetch(data, at(3 * i + 2), 0);
  mat3 S = mat3(d0.w, d1.x, d1.y, d1.x, d1.z, d1.w, d1.y, d1.w, d2.x);
  mat3 C = rot * S * transpose(rot);
  float iz = 1.0 / p.z;
  vec3 j0 = vec3(focal * iz, 0.0, -focal * p.x * iz * iz);
  vec3 j1 = vec3(0.0, focal * iz, -focal * p.y * iz * iz);
  // the 2D covariance (grown for a preview sample, splat budget below) + the avatar's low-pass, px^2
  float a = grow * dot(j0, C * j0) + lowPass, b = grow * dot(j0, C * j1);
  float c = grow * dot(j1, C * j1) + lowPass;
  float mid = 0.5 * (a + c), rad = sqrt(max(0.25 * (a - c) * (a - c) + b * b, 0.0));
  float l1 = mid + rad, l2 = max(mid - rad, 0.1);
  vec2 v1 = abs(b) > 1e-12 ? normalize(vec2(b, l1 - a)) : (a >= c ? vec2(1.0, 0.0) : vec2(0.0, 1.0));
  vec2 v2 = vec2(-v1.y, v1.x);
  vColor = texelFetch(colors, at(i), 0);
  float r = min(sqrt(max(2.0 * log(255.0 * vColor.a), 0.0)), 3.0);  // a exp(-r^2 / 2) = 1/255
  if (r <= 0.0) return;
  vec2 px = vec2(focal * p.x * iz, focal * p.y * iz) + 0.5 * size + r * (corner.x * sqrt(l1) * v1 + corner.y * sqrt(l2) * v2);
  gl_Position = vec4(px.x / size.x * 2.0 - 1.0, 1.0 - px.y / size.y * 2.0, 0.0, 1.0);
  vQ = r * corner;
}`;
const SPLAT_FS = `#version 300 es
precision highp float;
in vec4 vColor; in vec2 vQ; out vec4 frag;
void main() {
  float alpha = vColor.a * exp(-0.5 * dot(vQ, vQ));
  if (alpha < 1.0 / 255.0) discard;
  frag = vec4(vColor.rgb * alpha, alpha);
}`;
const SPLAT_TEX_W = 4096, SPLAT_SETTLE_MS = 250, SPLAT_TIME_EVERY = 8, SPLAT_PREVIEW_GROW = 0.6;
const SPLAT_LOD = {enabled: true, splatMs: 10, minSplats: 2000, measureScale: 1, holdPreview: false};

class SplatRenderer {
  constructor(canvas, background, options = {}) {
    const gl = canvas.getContext("webgl2", {antialias: false, premultipliedAlpha: true});
    if (!gl) throw new Error("this browser has no WebGL2");
    this.gl = gl; this.canvas = canvas; this.background = background; this.count = 0;
    this.movingScale = 1; this.lastMoved = -Infinity; this.drawnScale = 1; this.animating = false;
    if (!(options.lowPass >= 0)) throw new Error("SplatRenderer: options.lowPass (px^2, the avatar's) is required");
    this.lowPass = options.lowPass;
    this.lod = {...SPLAT_LOD, ...(options.lod || {})};
    this.msPerSplat = null; this.untimed = 0; this.drawnSplats = 0; this.draws = 0; this.ranked = 0; this.due = false;
    this.stats = {gaussians: 0, budget: 0, drawn: 0, moving: 0, rest: 0, usPerSplat: null, timed: 0};
    window.__splatStats = this.stats;
    const prog = gl.createProgram();
    for (const [type, src] of [[gl.VERTEX_SHADER, SPLAT_VS], [gl.FRAGMENT_SHADER, SPLAT_FS]]) {
      const sh = gl.createShader(type); gl.shaderSource(sh, src); gl.compileShader(sh);
      if (!gl.getShaderParameter(sh, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(sh));
      gl.attachShader(prog, sh);
    }
    gl.linkProgram(prog);
    if (!gl.getProgramParameter(prog, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(prog));
    this.prog = prog; gl.useProgram(prog);
    this.vao = gl.createVertexArray(); gl.bindVertexArray(this.vao);
    this.ibuf = gl.createBuffer(); this.capacity = 0;
    this.tex = {};
    for (const [name, unit] of [["data", 0], ["order", 1], ["colors", 2]]) {
      const t = gl.createTexture(); gl.activeTexture(gl.TEXTURE0 + unit); gl.bindTexture(gl.TEXTURE_2D, t);
      for (const p of [gl.TEXTURE_MIN_FILTER, gl.TEXTURE_MAG_FILTER]) gl.texParameteri(gl.TEXTURE_2D, p, gl.NEAREST);
      gl.uniform1i(gl.getUniformLocation(prog, name), unit);
      this.tex[name] = [t, unit];
    }
    this.U = {};
    for (const name of ["rot", "eye", "size", "focal", "grow", "lowPass"]) this.U[name] = gl.getUniformLocation(prog, name);
    gl.disable(gl.DEPTH_TEST); gl.enable(gl.BLEND); gl.blendFunc(gl.ONE, gl.ONE_MINUS_SRC_ALPHA);
    this.sortedFor = null;
  }

  _upload(name, internal, format, type, texels, per, array) {  // texels [count * per], rows of SPLAT_TEX_W texels
    const gl = this.gl, [t, unit] = this.tex[name], rows = Math.max(1, Math.ceil(texels / SPLAT_TEX_W));
    const full = new array.constructor(rows * SPLAT_TEX_W * per); full.set(array);
    gl.activeTexture(gl.TEXTURE0 + unit); gl.bindTexture(gl.TEXTURE_2D, t);
    gl.texImage2D(gl.TEXTURE_2D, 0, internal, SPLAT_TEX_W, rows, 0, format, type, full);
  }

  setSplats(centers, cov, rgba) {
    const gl = this.gl, g = centers.length / 3;
    const packed = new Float32Array(12 * g);  // 3 RGBA32F texels a Gaussian: centre, the 6 covariance terms
    for (let i = 0; i < g; i++) {
      packed.set(centers.subarray(3 * i, 3 * i + 3), 12 * i); packed.set(cov.subarray(6 * i, 6 * i + 6), 12 * i + 3);
    }
    this._upload("data", gl.RGBA32F, gl.RGBA, gl.FLOAT, 3 * g, 4, packed);
    this._upload("colors", gl.RGBA8, gl.RGBA, gl.UNSIGNED_BYTE, g, 4, rgba);
    if (g > this.capacity) {
      const idx = new Uint32Array(6 * g);
      for (let j = 0; j < g; j++) {
        const o = 6 * j, v = 4 * j;
        idx[o] = v; idx[o + 1] = v + 1; idx[o + 2] = v + 2; idx[o + 3] = v + 1; idx[o + 4] = v + 3; idx[o + 5] = v + 2;
      }
      gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, this.ibuf); gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, idx, gl.STATIC_DRAW);
      this.capacity = g;
    }
    this.centers = centers; this.cov = cov; this.rgba = rgba; this.count = g; this.sortedFor = null;
    this.stats.gaussians = g;
    if (!this.order || this.order.length < g) { this.order = new Uint32Array(g); this.key = new Uint16Array(g);
                                                 this.depth = new Float32Array(g); this.rank = new Uint32Array(g); }
    if (this.lod.enabled) this.lastMoved = performance.now();  // a new frame: drawn with the budget first
  }

  _rank() {  // this.rank: a fixed pseudo-random permutation of the G Gaussians (its prefix: a uniform sample)
    const g = this.count, rank = this.rank;
    for (let i = 0; i < g; i++) rank[i] = i;
    let seed = 12345;
    for (let i = g - 1; i > 0; i--) {
      seed = (Math.imul(seed, 1103515245) + 12345) >>> 0;
      const j = seed % (i + 1), t = rank[i]; rank[i] = rank[j]; rank[j] = t;
    }
    this.ranked = g;
  }

  get budget() {  // Gaussians drawn while the view moves
    const g = this.count;
    if (!this.lod.enabled || this.msPerSplat === null) return g;
    const m = Math.floor(this.lod.splatMs / this.msPerSplat);
    return Math.max(Math.min(this.lod.minSplats, g), Math.min(m, g));
  }

  get moving() {
    return this.animating || this.lod.holdPreview || performance.now() - this.lastMoved < SPLAT_SETTLE_MS;
  }

  budgetText() {  // the budget for the page's status line
    const f = n => n.toLocaleString("en-US"), g = this.count, m = this.budget;
    if (!this.lod.enabled || !g || m >= g) return g ? `${f(g)} splats` : "";
    return this.drawnSplats < g ? `preview ${f(m)} / ${f(g)} splats while moving`
                                : `${f(g)} splats (preview ${f(m)} while moving)`;
  }

  _sort(eye, fwd, m) {  // back to front: a 16-bit counting sort of the depths along the view axis of the m drawn
    const g = this.count, c = this.centers, depth = this.depth, key = this.key, order = this.order;
    if (m < g && this.ranked !== g) this._rank();
    const sel = m < g ? this.rank : null;  // the sample, or all
    let lo = Infinity, hi = -Infinity;
    for (let j = 0; j < m; j++) {
      const i = sel ? sel[j] : j;
      const d = (c[3 * i] - eye[0]) * fwd[0] + (c[3 * i + 1] - eye[1]) * fwd[1] + (c[3 * i + 2] - eye[2]) * fwd[2];
      depth[j] = d; if (d < lo) lo = d; if (d > hi) hi = d;
    }
    const scale = 65535 / Math.max(hi - lo, 1e-9), counts = new Uint32Array(65537);
    for (let j = 0; j < m; j++) { key[j] = 65535 - Math.floor((depth[j] - lo) * scale); counts[key[j] + 1]++; }
    for (let k = 1; k < 65537; k++) counts[k] += counts[k - 1];
    for (let j = 0; j < m; j++) order[counts[key[j]]++] = sel ? sel[j] : j;
    const gl = this.gl;
    this._upload("order", gl.R32UI, gl.RED_INTEGER, gl.UNSIGNED_INT, m, 1, order.subarray(0, m));
  }

  moved() { this.lastMoved = performance.now(); this.due = true; }

  get settling() {  // a redraw is due: moved, or the image is not the one due now (all at rest, another budget)
    const moving = this.moving;
    return this.due || this.drawnScale !== (moving ? this.movingScale : 1)
      || this.drawnSplats !== (moving ? this.budget : this.count);
  }

  draw(view) {
    const moving = this.moving, t0 = performance.now();
    this.due = false;
    this.drawnScale = moving ? this.movingScale : 1;
    const gl = this.gl, canvas = this.canvas, s = this.drawnScale * (window.devicePixelRatio || 1);
    const w = Math.max(1, Math.round(canvas.clientWidth * s)), h = Math.max(1, Math.round(canvas.clientHeight * s));
    if (canvas.width !== w || canvas.height !== h) { canvas.width = w; canvas.height = h; }
    const m = moving ? this.budget : this.count, key = [m, ...view.eye, ...view.fwd].join(",");
    if (this.count && this.sortedFor !== key) { this._sort(view.eye, view.fwd, m); this.sortedFor = key; }
    gl.useProgram(this.prog); gl.bindVertexArray(this.vao);
    gl.viewport(0, 0, w, h);
    const bg = this.background; gl.clearColor(bg[0], bg[1], bg[2], 1); gl.clear(gl.COLOR_BUFFER_BIT);
    if (!this.count) { this.drawnSplats = 0; return; }
    const r = view.right, d = view.down, f = view.fwd;
    gl.uniformMatrix3fv(this.U.rot, false, new Float32Array([r[0], d[0], f[0], r[1], d[1], f[1], r[2], d[2], f[2]]));
    gl.uniform3fv(this.U.eye, view.eye); gl.uniform2f(this.U.size, w, h);
    gl.uniform1f(this.U.focal, 0.5 * h / Math.tan(view.fov / 2)); gl.uniform1f(this.U.lowPass, this.lowPass);
    gl.uniform1f(this.U.grow, m < this.count ? (this.count / m) ** SPLAT_PREVIEW_GROW : 1);
    gl.drawElements(gl.TRIANGLES, 6 * m, gl.UNSIGNED_INT, 0);
    this.drawnSplats = m; this.draws++;
    const st = this.stats; st.drawn = m; st.budget = this.budget; if (moving) st.moving = m; else st.rest = m;
    // the cost of a drawn splat, from full draws timed to completion: each one at rest, one in SPLAT_TIME_EVERY
    // while all are drawn moving (a hardware GPU, or G under the budget); the first draw compiles the shaders
    const timed = this.lod.enabled && m === this.count && this.draws > 1
      && (this.msPerSplat === null || !moving || ++this.untimed >= SPLAT_TIME_EVERY);
    if (timed) {
      gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, this.pixel || (this.pixel = new Uint8Array(4)));
      const ms = (performance.now() - t0) * this.lod.measureScale / m;
      this.msPerSplat = this.msPerSplat === null ? ms : 0.5 * (this.msPerSplat + ms);
      this.untimed = 0; st.timed++; st.usPerSplat = Math.round(1000 * this.msPerSplat * 100) / 100;
      st.budget = this.budget;
    }
  }
}

const vnorm = v => { const l = Math.hypot(...v) || 1; return v.map(x => x / l); };
const vcross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];

function orbitBasis(up) {  // two unit vectors orthogonal to `up`: azimuth 0 and pi/2
  const e1 = vnorm(vcross(up, Math.abs(up[0]) < 0.9 ? [1, 0, 0] : [0, 1, 0]));
  return [e1, vcross(up, e1)];
}

function orbitView(cam) {  // {target, up, az, el, radius, fov} -> {eye, right, down, fwd, fov}
  const up = vnorm(cam.up), [e1, e2] = orbitBasis(up);
  const dir = [0, 1, 2].map(k => Math.cos(cam.el) * (Math.cos(cam.az) * e1[k] + Math.sin(cam.az) * e2[k])
                                 + Math.sin(cam.el) * up[k]);
  const eye = cam.target.map((x, k) => x + cam.radius * dir[k]);
  const fwd = dir.map(x => -x), right = vnorm(vcross(fwd, up)), down = vcross(fwd, right);
  return {eye, right, down, fwd, fov: cam.fov};
}

function OrbitControls(canvas, cam, onChange) {  // drag: orbit; wheel: zoom; onChange() after each change
  let drag = null;
  canvas.style.touchAction = "none";
  canvas.addEventListener("pointerdown", e => { drag = [e.clientX, e.clientY]; canvas.setPointerCapture(e.pointerId); });
  canvas.addEventListener("pointerup", () => { drag = null; });
  canvas.addEventListener("pointermove", e => {
    if (!drag) return;
    cam.az -= (e.clientX - drag[0]) * 0.008;
    cam.el = Math.max(-1.5, Math.min(1.5, cam.el + (e.clientY - drag[1]) * 0.008));
    drag = [e.clientX, e.clientY]; onChange();
  });
  canvas.addEventListener("wheel", e => { cam.radius *= Math.exp(e.deltaY * 0.001); onChange(); e.preventDefault(); },
                          {passive: false});
}
"""
