"""NVIDIA Warp kernels of the 3DGS rasterizer (forward and backward), two ways to walk the work:

- tile walk (`*_tiles`, the CPU variant): one job per 16x16 tile visits the tile's depth-sorted splats and, for each
  splat, only the tile's pixels on each row's chord of its alpha >= 1/255 ellipse (`_row_span`). Per-pixel state
  lives in global per-pixel arrays; a tile owns its pixels, so jobs never race. The backward pass sums a splat's
  gradient over its pixels in registers and adds it once per tile. On one CPU core this is ~4x faster than one job
  per pixel (benchmarks/splat_bench).
- pixel walk (`*_pixels`, the GPU variant): one thread per pixel walks its tile's list (CUDA blocks of 256 threads
  are one tile, so they read the same splats); gradients are added with atomics, once per (splat, pixel).

Both give the same numbers and both run on CPU and CUDA. The semantics are those of `_torch_impl` (its docstring);
the gradients are derived in `backward_tiles`; the backward kernels compute only those they are asked for
(`want_colors`, `want_alpha`: the colours' gradient, the ones through alpha). Colours are Warp vectors of any length
(vec3, vec4, ...): the kernels are generic over that type. A launch covers the tiles `tile_order[first + i * step]`,
so several launches (one per CPU thread) can share an image; `tile_order` lists the busiest tiles first, which
balances them. Warp's CPU atomics are plain adds: concurrent launches need their own gradient arrays.

`count_tiles` and `fill_tiles` bin the splats on the CPU without a sort of the (tile, depth) pairs: a bucket sort by
tile of the splats taken in depth order.

Importing this module imports Warp but compiles nothing; Warp builds the kernels on first launch (cached on disk).
"""

from __future__ import annotations

from typing import Any

import warp as wp

from avatarctl.splat._torch_impl import ALPHA_MAX, ALPHA_MIN, T_MIN, TILE
from avatarctl.splat.density import SH_C0, SH_C1

wp.set_module_options({"enable_backward": False})  # the adjoints are written by hand below

_TILE = wp.constant(TILE)
_PIXELS_PER_TILE = wp.constant(TILE * TILE)
_ALPHA_MIN = wp.constant(ALPHA_MIN)
_ALPHA_MAX = wp.constant(ALPHA_MAX)
_T_MIN = wp.constant(T_MIN)
_SH_C0 = wp.constant(SH_C0)
_SH_C1 = wp.constant(SH_C1)


@wp.func
def _raw_alpha(dx: float, dy: float, conic: wp.vec3, opacity: float) -> float:
    """o exp(power), power = -0.5 d^T Sigma2d^-1 d at d = pixel - mean; 0 where power > 0 (the splat is skipped).
    The splat counts where min(ALPHA_MAX, this) >= ALPHA_MIN."""
    power = -0.5 * (conic[0] * dx * dx + conic[2] * dy * dy) - conic[1] * dx * dy
    if power > 0.0:
        return 0.0
    return opacity * wp.exp(power)


@wp.func
def _power_cutoff(opacity: float) -> float:
    """The power below which the splat is fainter than ALPHA_MIN, lowered by a margin of 0.05 (~5 % in alpha) so
    that float error in `_row_span` never drops a pixel that counts; +1 where no pixel can count."""
    if opacity < _ALPHA_MIN:
        return 1.0
    return wp.log(_ALPHA_MIN / opacity) - 0.05


@wp.func
def _row_span(y: int, mean: wp.vec2, conic: wp.vec3, cutoff: float, x0: int, x1: int) -> wp.vec2i:
    """The pixels x0 <= x <= x1 of row y inside the ellipse power = cutoff (`_power_cutoff`), widened by 0.01 px:
    (xa, xb), empty when xb < xa. Only a speed-up: the pixels inside are tested exactly."""
    a = conic[0]
    if cutoff > 0.0:
        return wp.vec2i(0, -1)
    if a <= 0.0:  # not positive definite: no ellipse, keep the row
        return wp.vec2i(x0, x1)
    dy = float(y) - mean[1]
    # power >= cutoff  <=>  0.5 a dx^2 + b dy dx + 0.5 c dy^2 + cutoff <= 0
    disc = conic[1] * conic[1] * dy * dy - a * (conic[2] * dy * dy + 2.0 * cutoff)
    if disc < 0.0:
        return wp.vec2i(0, -1)
    root = wp.sqrt(disc)
    lo = wp.clamp(mean[0] + (-conic[1] * dy - root) / a - 0.01, -1.0e6, 1.0e6)
    hi = wp.clamp(mean[0] + (-conic[1] * dy + root) / a + 0.01, -1.0e6, 1.0e6)
    return wp.vec2i(wp.max(x0, int(wp.ceil(lo))), wp.min(x1, int(wp.floor(hi))))


@wp.func
def _tile_rect(tile: int, tiles_x: int, width: int, height: int) -> wp.vec4i:
    """The pixels of a tile, clipped to the image: (x0, y0, x1, y1) inclusive."""
    x0 = (tile % tiles_x) * _TILE
    y0 = (tile // tiles_x) * _TILE
    return wp.vec4i(x0, y0, wp.min(x0 + _TILE, width) - 1, wp.min(y0 + _TILE, height) - 1)


@wp.func
def _pixel_of_thread(i: int, tile_order: wp.array(dtype=wp.int32), first: int, step: int, tiles_x: int) -> wp.vec3i:
    """Pixel-walk thread i -> (tile, x, y): 256 consecutive threads cover one tile (may lie outside the image)."""
    tile = tile_order[first + (i // _PIXELS_PER_TILE) * step]
    x = (tile % tiles_x) * _TILE + (i % _PIXELS_PER_TILE) % _TILE
    y = (tile // tiles_x) * _TILE + (i % _PIXELS_PER_TILE) // _TILE
    return wp.vec3i(tile, x, y)


@wp.kernel
def count_tiles(boxes: wp.array(dtype=wp.vec4i),  # [G] pixels the splat may count at (x0, y0, x1, y1)
                tiles_x: int, counts: wp.array(dtype=wp.int32)):  # [tiles] zeroed, added to
    g = wp.tid()
    box = boxes[g]
    if box[0] > box[2] or box[1] > box[3]:
        return
    for ty in range(box[1] // _TILE, box[3] // _TILE + 1):
        for tx in range(box[0] // _TILE, box[2] // _TILE + 1):
            wp.atomic_add(counts, ty * tiles_x + tx, 1)


@wp.kernel
def count_entries(boxes: wp.array(dtype=wp.vec4i), entries: wp.array(dtype=wp.int32)):  # [G] out: tiles touched
    g = wp.tid()
    box = boxes[g]
    n = int(0)
    if box[0] <= box[2] and box[1] <= box[3]:
        n = (box[2] // _TILE - box[0] // _TILE + 1) * (box[3] // _TILE - box[1] // _TILE + 1)
    entries[g] = n


@wp.kernel
def list_entries(boxes: wp.array(dtype=wp.vec4i), tiles_x: int,
                 ends: wp.array(dtype=wp.int32),  # [G] inclusive cumulative sum of count_entries
                 tiles: wp.array(dtype=wp.int32), splats: wp.array(dtype=wp.int32)):  # [entries] out
    # splat g's (tile, g) entries in rows of tiles, from ends[g - 1]: the order of a splat-major enumeration
    g = wp.tid()
    box = boxes[g]
    if box[0] > box[2] or box[1] > box[3]:
        return
    i = int(0)
    if g > 0:
        i = ends[g - 1]
    for ty in range(box[1] // _TILE, box[3] // _TILE + 1):
        for tx in range(box[0] // _TILE, box[2] // _TILE + 1):
            tiles[i] = ty * tiles_x + tx
            splats[i] = g
            i += 1


@wp.kernel
def fill_tiles(order: wp.array(dtype=wp.int32),  # [visible] splat indices front to back (stable)
               boxes: wp.array(dtype=wp.vec4i), tiles_x: int,
               cursor: wp.array(dtype=wp.int32),  # [tiles] in: each tile's first entry; out: one past its last
               ids: wp.array(dtype=wp.int32)):  # [entries] out
    # One job (launch dim 1): appending the splats in depth order keeps every tile's list sorted by depth.
    for i in range(order.shape[0]):
        g = order[i]
        box = boxes[g]
        if box[0] > box[2] or box[1] > box[3]:
            continue
        for ty in range(box[1] // _TILE, box[3] // _TILE + 1):
            for tx in range(box[0] // _TILE, box[2] // _TILE + 1):
                t = ty * tiles_x + tx
                ids[cursor[t]] = g
                cursor[t] = cursor[t] + 1


@wp.func
def _footprint(m: wp.vec2, radius: int, width: int, height: int) -> wp.vec4i:
    """`project.footprint` of one splat: mean +- radius clipped to the image, (0, 0, -1, -1) when culled."""
    if radius <= 0:
        return wp.vec4i(0, 0, -1, -1)
    r = float(radius)
    return wp.vec4i(int(wp.max(wp.ceil(m[0] - r), 0.0)), int(wp.max(wp.ceil(m[1] - r), 0.0)),
                    int(wp.min(wp.floor(m[0] + r), float(width) - 1.0)),
                    int(wp.min(wp.floor(m[1] + r), float(height) - 1.0)))


@wp.kernel
def project_reach(means: wp.array(dtype=wp.vec3),  # [G] world, metres
                  covars: wp.array(dtype=wp.mat33),  # [G] world covariance, metres^2
                  opacities: wp.array(dtype=float),  # [G]
                  cam_K: wp.array(dtype=wp.mat33), cam_R: wp.array(dtype=wp.mat33),  # [1] each
                  cam_T: wp.array(dtype=wp.vec3),  # [1]
                  width: int, height: int, near: float, low_pass: float, fov_margin: float,
                  means2d: wp.array(dtype=wp.vec2), conics: wp.array(dtype=wp.vec3),  # [G] out
                  depths: wp.array(dtype=float), radii: wp.array(dtype=wp.int32),  # [G] out
                  boxes: wp.array(dtype=wp.vec4i)):  # [G] out: rasterizer.reach
    # project.project_gaussians (one camera) followed by rasterizer.reach, fused for rendering without
    # gradients: the same formulas in the same order (their docstrings hold the maths).
    g = wp.tid()
    K = cam_K[0]
    R = cam_R[0]
    t = R * means[g] + cam_T[0]
    z = t[2]
    in_front = z > near
    inv_z = 1.0
    if in_front:
        inv_z = 1.0 / z
    x = t[0] * inv_z
    y = t[1] * inv_z
    fx, skew, cx, fy, cy = K[0, 0], K[0, 1], K[0, 2], K[1, 1], K[1, 2]
    w = float(width)
    h = float(height)
    xc = wp.clamp(x, -(cx / fx + fov_margin * 0.5 * w / fx), (w - cx) / fx + fov_margin * 0.5 * w / fx)
    yc = wp.clamp(y, -(cy / fy + fov_margin * 0.5 * h / fy), (h - cy) / fy + fov_margin * 0.5 * h / fy)
    r0 = wp.vec3(R[0, 0], R[0, 1], R[0, 2])
    r1 = wp.vec3(R[1, 0], R[1, 1], R[1, 2])
    r2 = wp.vec3(R[2, 0], R[2, 1], R[2, 2])
    row_x = (r0 - xc * r2) * inv_z
    row_y = (r1 - yc * r2) * inv_z
    m0 = fx * row_x + skew * row_y
    m1 = fy * row_y
    S = covars[g]
    s0 = S * m0
    s1 = S * m1
    a = wp.dot(m0, s0) + low_pass
    b = wp.dot(m1, s0)
    c = wp.dot(m1, s1) + low_pass
    det = a * c - b * b
    ok = in_front and det > 0.0 and wp.isfinite(det)
    mean = wp.vec2(0.0, 0.0)
    conic = wp.vec3(0.0, 0.0, 0.0)
    radius = int(0)
    if ok:
        inv_det = 1.0 / det
        conic = wp.vec3(c * inv_det, -b * inv_det, a * inv_det)
        mean = wp.vec2(fx * x + skew * y + cx, fy * y + cy)
        mid = 0.5 * (a + c)
        radius = int(wp.ceil(3.0 * wp.sqrt(mid + wp.sqrt(wp.max(mid * mid - det, 0.0)))))
    box = _footprint(mean, radius, width, height)
    if box[0] > box[2] or box[1] > box[3]:
        radius = 0
        box = wp.vec4i(0, 0, -1, -1)
    means2d[g] = mean
    conics[g] = conic
    depths[g] = z
    radii[g] = radius
    # reach: the footprint cut to the box of the ellipse o exp(power) >= ALPHA_MIN, widened by 0.05 in power and 1 px
    o = opacities[g]
    r2sq = 2.0 * (wp.log(wp.max(o / _ALPHA_MIN, 1.0e-30)) + 0.05)
    if not (r2sq > 0.0):
        boxes[g] = wp.vec4i(0, 0, -1, -1)
        return
    cdet = conic[0] * conic[2] - conic[1] * conic[1]
    if cdet > 0.0 and conic[0] > 0.0:
        ex = wp.sqrt(wp.max(r2sq * conic[2] / cdet, 0.0))
        ey = wp.sqrt(wp.max(r2sq * conic[0] / cdet, 0.0))
        lo_x = int(wp.floor(wp.clamp(mean[0] - ex - 1.0, -1.0e6, 1.0e6)))
        lo_y = int(wp.floor(wp.clamp(mean[1] - ey - 1.0, -1.0e6, 1.0e6)))
        hi_x = int(wp.ceil(wp.clamp(mean[0] + ex + 1.0, -1.0e6, 1.0e6)))
        hi_y = int(wp.ceil(wp.clamp(mean[1] + ey + 1.0, -1.0e6, 1.0e6)))
        box = wp.vec4i(wp.max(box[0], lo_x), wp.max(box[1], lo_y), wp.min(box[2], hi_x), wp.min(box[3], hi_y))
    boxes[g] = box


@wp.kernel
def transformed_covariances(linear: wp.array(dtype=wp.mat33),  # [B * N] one linear map per group
                            quats: wp.array(dtype=wp.vec4),  # [N * K] (w, x, y, z), any norm
                            log_scales: wp.array(dtype=wp.vec3),  # [N * K] log metres
                            per_group: int, groups: int,  # K, N
                            covars: wp.array(dtype=wp.mat33)):  # [B * N * K] out
    # covariance.transformed_covariances without gradients: Sigma = M M^T, M = A R(q) diag(exp(s))
    i = wp.tid()
    gk = i % (groups * per_group)
    q = quats[gk]
    q = q / wp.max(wp.length(q), 1.0e-12)
    w, x, y, z = q[0], q[1], q[2], q[3]
    R = wp.mat33(1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y),
                 2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x),
                 2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y))
    s = log_scales[gk]
    M = wp.mul(linear[i // per_group], wp.mul(R, wp.diag(wp.vec3(wp.exp(s[0]), wp.exp(s[1]), wp.exp(s[2])))))
    covars[i] = wp.mul(M, wp.transpose(M))


@wp.func
def _cell_box(mean: wp.vec3, half: wp.vec3, lo: wp.vec3, cell: float, dims: wp.vec3i) -> wp.spatial_vectorf:
    """The cells (x0, y0, z0, x1, y1, z1), inclusive, that the box mean +- half overlaps, clipped to the grid (as
    floats; x0 > x1 when it misses)."""
    a = wp.cw_div(mean - half - lo, wp.vec3(cell, cell, cell))
    b = wp.cw_div(mean + half - lo, wp.vec3(cell, cell, cell))
    return wp.spatial_vectorf(wp.max(wp.floor(a[0]), 0.0), wp.max(wp.floor(a[1]), 0.0), wp.max(wp.floor(a[2]), 0.0),
                              wp.min(wp.floor(b[0]), float(dims[0] - 1)), wp.min(wp.floor(b[1]), float(dims[1] - 1)),
                              wp.min(wp.floor(b[2]), float(dims[2] - 1)))


@wp.kernel
def count_cells(means: wp.array(dtype=wp.vec3), halves: wp.array(dtype=wp.vec3), lo: wp.vec3, cell: float,
                dims: wp.vec3i, counts: wp.array(dtype=wp.int32)):  # [cells] zeroed, added to
    g = wp.tid()
    box = _cell_box(means[g], halves[g], lo, cell, dims)
    for z in range(int(box[2]), int(box[5]) + 1):
        for y in range(int(box[1]), int(box[4]) + 1):
            for x in range(int(box[0]), int(box[3]) + 1):
                wp.atomic_add(counts, (z * dims[1] + y) * dims[0] + x, 1)


@wp.kernel
def fill_cells(means: wp.array(dtype=wp.vec3), halves: wp.array(dtype=wp.vec3), lo: wp.vec3, cell: float,
               dims: wp.vec3i, cursor: wp.array(dtype=wp.int32),  # [cells] in: each cell's first entry
               ids: wp.array(dtype=wp.int32)):  # [entries] out: Gaussian indices by cell
    g = wp.tid()
    box = _cell_box(means[g], halves[g], lo, cell, dims)
    for z in range(int(box[2]), int(box[5]) + 1):
        for y in range(int(box[1]), int(box[4]) + 1):
            for x in range(int(box[0]), int(box[3]) + 1):
                ids[wp.atomic_add(cursor, (z * dims[1] + y) * dims[0] + x, 1)] = g


@wp.kernel
def density_at_points(points: wp.array(dtype=wp.vec3), dirs: wp.array(dtype=wp.vec3),
                      lo: wp.vec3, cell: float, dims: wp.vec3i,
                      cell_start: wp.array(dtype=wp.int32),  # [cells + 1]
                      ids: wp.array(dtype=wp.int32),  # [entries] sorted by cell, then Gaussian
                      means: wp.array(dtype=wp.vec3), precisions: wp.array(dtype=wp.mat33),
                      weights: wp.array(dtype=float),  # [G] peak density of each Gaussian
                      sh: wp.array2d(dtype=float),  # [G, 3 S] SH coefficients, (S, 3) row-major; S = 1 or 4
                      dir_maps: wp.array(dtype=wp.mat33),  # [G] world direction -> the Gaussian's SH frame
                      cutoff2: float,
                      sigma: wp.array(dtype=float), rgb: wp.array(dtype=wp.vec3)):  # [P] out
    # splat.density.gaussian_field_at: the Gaussians listed in the point's cell, within the Mahalanobis cut-off
    p = wp.tid()
    x = points[p]
    c = wp.cw_div(x - lo, wp.vec3(cell, cell, cell))
    total = float(0.0)
    acc = wp.vec3(0.0, 0.0, 0.0)
    if c[0] >= 0.0 and c[1] >= 0.0 and c[2] >= 0.0 and c[0] < float(dims[0]) and c[1] < float(dims[1]) and \
            c[2] < float(dims[2]):
        k = (int(c[2]) * dims[1] + int(c[1])) * dims[0] + int(c[0])
        S = sh.shape[1] // 3
        for e in range(cell_start[k], cell_start[k + 1]):
            g = ids[e]
            d = x - means[g]
            q = wp.dot(d, precisions[g] * d)
            if q <= cutoff2:
                w = weights[g] * wp.exp(-0.5 * q)
                col = wp.vec3(sh[g, 0], sh[g, 1], sh[g, 2]) * _SH_C0
                if S > 1:
                    v = wp.normalize(dir_maps[g] * dirs[p])
                    col = col - _SH_C1 * v[1] * wp.vec3(sh[g, 3], sh[g, 4], sh[g, 5]) \
                        + _SH_C1 * v[2] * wp.vec3(sh[g, 6], sh[g, 7], sh[g, 8]) \
                        - _SH_C1 * v[0] * wp.vec3(sh[g, 9], sh[g, 10], sh[g, 11])
                col = wp.vec3(wp.max(col[0] + 0.5, 0.0), wp.max(col[1] + 0.5, 0.0), wp.max(col[2] + 0.5, 0.0))
                total += w
                acc += w * col
    sigma[p] = total
    rgb[p] = acc


@wp.kernel
def forward_tiles(tile_order: wp.array(dtype=wp.int32), first: int, step: int,  # tiles of this launch
                  tiles_x: int, width: int, height: int,
                  tile_start: wp.array(dtype=wp.int32),  # [tiles + 1] range of each tile in ids
                  ids: wp.array(dtype=wp.int32),  # [entries] splat index, sorted by (tile, depth)
                  boxes: wp.array(dtype=wp.vec4i),  # [G] pixels it may count at (rasterizer.reach), inclusive
                  means2d: wp.array(dtype=wp.vec2),  # [G]
                  conics: wp.array(dtype=wp.vec3),  # [G]
                  colors: wp.array(dtype=Any),  # [G] vecC
                  opacities: wp.array(dtype=float),  # [G]
                  background: wp.array(dtype=Any),  # [1] vecC
                  rgb: wp.array(dtype=Any),  # [H * W] vecC out
                  transmittance: wp.array(dtype=float),  # [H * W] out: T_final
                  last: wp.array(dtype=wp.int32),  # [H * W] out: 1 + position in ids of the last contributor, 0: none
                  row_alive: wp.array(dtype=wp.int32)):  # [tiles * 16] scratch: unfinished pixels of each tile row
    # A finished pixel keeps -T in `transmittance` until the end (T >= T_MIN > 0); rows with no unfinished pixel
    # are skipped without a look at their pixels.
    tile = tile_order[first + wp.tid() * step]
    rect = _tile_rect(tile, tiles_x, width, height)
    tx0, ty0, tx1, ty1 = rect[0], rect[1], rect[2], rect[3]
    bg = background[0]
    for y in range(ty0, ty1 + 1):
        row_alive[tile * _TILE + y - ty0] = tx1 - tx0 + 1
        for x in range(tx0, tx1 + 1):
            p = y * width + x
            rgb[p] = bg * 0.0
            transmittance[p] = 1.0
            last[p] = 0
    left = (tx1 - tx0 + 1) * (ty1 - ty0 + 1)  # pixels not finished
    for k in range(tile_start[tile], tile_start[tile + 1]):
        if left == 0:
            break
        g = ids[k]
        box = boxes[g]
        mean = means2d[g]
        conic = conics[g]
        opacity = opacities[g]
        cutoff = _power_cutoff(opacity)
        color = colors[g]
        for y in range(wp.max(box[1], ty0), wp.min(box[3], ty1) + 1):
            row = tile * _TILE + y - ty0
            if row_alive[row] == 0:
                continue
            span = _row_span(y, mean, conic, cutoff, wp.max(box[0], tx0), wp.min(box[2], tx1))
            for x in range(span[0], span[1] + 1):
                p = y * width + x
                t = transmittance[p]
                if t > 0.0:
                    alpha = wp.min(_ALPHA_MAX, _raw_alpha(float(x) - mean[0], float(y) - mean[1], conic, opacity))
                    if alpha >= _ALPHA_MIN:
                        t_next = t * (1.0 - alpha)
                        if t_next < _T_MIN:
                            transmittance[p] = -t
                            row_alive[row] = row_alive[row] - 1
                            left -= 1
                        else:
                            rgb[p] = rgb[p] + color * (t * alpha)
                            transmittance[p] = t_next
                            last[p] = k + 1
    for y in range(ty0, ty1 + 1):
        for x in range(tx0, tx1 + 1):
            p = y * width + x
            t = wp.abs(transmittance[p])
            transmittance[p] = t
            rgb[p] = rgb[p] + bg * t


@wp.kernel
def forward_pixels(tile_order: wp.array(dtype=wp.int32), first: int, step: int,  # tiles of this launch
                   tiles_x: int, width: int, height: int,
                   tile_start: wp.array(dtype=wp.int32), ids: wp.array(dtype=wp.int32),
                   boxes: wp.array(dtype=wp.vec4i), means2d: wp.array(dtype=wp.vec2),
                   conics: wp.array(dtype=wp.vec3), colors: wp.array(dtype=Any), opacities: wp.array(dtype=float),
                   background: wp.array(dtype=Any), rgb: wp.array(dtype=Any),
                   transmittance: wp.array(dtype=float), last: wp.array(dtype=wp.int32),
                   row_alive: wp.array(dtype=wp.int32)):  # unused (the signature of forward_tiles)
    txy = _pixel_of_thread(wp.tid(), tile_order, first, step, tiles_x)
    tile, x, y = txy[0], txy[1], txy[2]
    if x >= width or y >= height:
        return
    bg = background[0]
    acc = bg * 0.0
    t = float(1.0)
    n = int(0)
    for k in range(tile_start[tile], tile_start[tile + 1]):
        g = ids[k]
        box = boxes[g]
        if x >= box[0] and x <= box[2] and y >= box[1] and y <= box[3]:
            mean = means2d[g]
            alpha = wp.min(_ALPHA_MAX, _raw_alpha(float(x) - mean[0], float(y) - mean[1], conics[g], opacities[g]))
            if alpha >= _ALPHA_MIN:
                t_next = t * (1.0 - alpha)
                if t_next < _T_MIN:
                    break
                acc = acc + colors[g] * (t * alpha)
                t = t_next
                n = k + 1
    p = y * width + x
    rgb[p] = acc + bg * t
    transmittance[p] = t
    last[p] = n


@wp.func
def _grad_alpha(grad_rgb: Any, grad_alpha: float, color: Any, behind: Any, t: float, t_final: float,
                one_minus_alpha: float) -> float:
    """dL/dalpha_i of one pixel: sum_c g_c T_i (c_i - B_c) + g_alpha T_final / (1 - alpha_i)."""
    return wp.dot(grad_rgb, color - behind) * t + grad_alpha * t_final / one_minus_alpha


@wp.kernel
def backward_tiles(tile_order: wp.array(dtype=wp.int32), first: int, step: int,  # tiles of this launch
                   tiles_x: int, width: int, height: int,
                   tile_start: wp.array(dtype=wp.int32), ids: wp.array(dtype=wp.int32),
                   boxes: wp.array(dtype=wp.vec4i), means2d: wp.array(dtype=wp.vec2),
                   conics: wp.array(dtype=wp.vec3), colors: wp.array(dtype=Any), opacities: wp.array(dtype=float),
                   background: wp.array(dtype=Any),
                   transmittance: wp.array(dtype=float),  # [H * W] T_final of the forward pass
                   last: wp.array(dtype=wp.int32),  # [H * W] of the forward pass
                   grad_rgb: wp.array(dtype=Any),  # [H * W] vecC dL/drgb
                   grad_alpha_out: wp.array(dtype=float),  # [H * W] dL/dalpha
                   t_scratch: wp.array(dtype=float),  # [H * W] scratch: T in front of the current splat
                   behind_scratch: wp.array(dtype=Any),  # [H * W] vecC scratch: colour seen behind it
                   row_last: wp.array(dtype=wp.int32),  # [tiles * 16] scratch: the largest `last` of each tile row
                   want_colors: int,  # 0: grad_colors is not required (left untouched)
                   want_alpha: int,  # 0: grad_means2d, grad_conics, grad_opacities are not required (left untouched)
                   grad_means2d: wp.array(dtype=wp.vec2),  # [G] out, added to
                   grad_conics: wp.array(dtype=wp.vec3),  # [G] out, added to
                   grad_colors: wp.array(dtype=Any),  # [G] vecC out, added to
                   grad_opacities: wp.array(dtype=float)):  # [G] out, added to
    # Walking back to front from each pixel's last contributor: T_i = T_{i+1} / (1 - alpha_i) (T_N = T_final) and
    # B_i = alpha_{i+1} c_{i+1} + (1 - alpha_{i+1}) B_{i+1} (B_N = background), the colour behind splat i, so that
    #   drgb_c/dalpha_i = T_i (c_i,c - B_i,c),  dalpha_out/dalpha_i = T_final / (1 - alpha_i),  drgb/dc_i = T_i alpha_i;
    # alpha_i = o_i exp(power) (unclamped) -> dalpha/do = exp(power), dalpha/dpower = alpha_i,
    # dpower/dmean = (a dx + b dy, b dx + c dy), dpower/d(a, b, c) = (-dx^2 / 2, -dx dy, -dy^2 / 2).
    # Only the gradients asked for (want_colors, want_alpha) are computed: T_i is needed by both, B_i only through
    # alpha.
    tile = tile_order[first + wp.tid() * step]
    rect = _tile_rect(tile, tiles_x, width, height)
    tx0, ty0, tx1, ty1 = rect[0], rect[1], rect[2], rect[3]
    bg = background[0]
    end = int(0)
    for y in range(ty0, ty1 + 1):
        row_end = int(0)
        for x in range(tx0, tx1 + 1):
            p = y * width + x
            t_scratch[p] = transmittance[p]
            behind_scratch[p] = bg
            row_end = wp.max(row_end, last[p])
        row_last[tile * _TILE + y - ty0] = row_end
        end = wp.max(end, row_end)
    start = tile_start[tile]
    for j in range(start, end):
        k = end - 1 - (j - start)
        g = ids[k]
        box = boxes[g]
        mean = means2d[g]
        conic = conics[g]
        opacity = opacities[g]
        cutoff = _power_cutoff(opacity)
        color = colors[g]
        g_mean = wp.vec2(0.0, 0.0)
        g_conic = wp.vec3(0.0, 0.0, 0.0)
        g_color = color * 0.0
        g_opacity = float(0.0)
        hit = int(0)
        for y in range(wp.max(box[1], ty0), wp.min(box[3], ty1) + 1):
            if k >= row_last[tile * _TILE + y - ty0]:
                continue
            dy = float(y) - mean[1]
            span = _row_span(y, mean, conic, cutoff, wp.max(box[0], tx0), wp.min(box[2], tx1))
            for x in range(span[0], span[1] + 1):
                p = y * width + x
                if k < last[p]:
                    dx = float(x) - mean[0]
                    raw = _raw_alpha(dx, dy, conic, opacity)
                    alpha = wp.min(_ALPHA_MAX, raw)
                    if alpha >= _ALPHA_MIN:
                        hit = 1
                        one_minus = 1.0 - alpha
                        t = t_scratch[p] / one_minus
                        t_scratch[p] = t
                        g_rgb = grad_rgb[p]
                        if want_colors != 0:
                            g_color = g_color + g_rgb * (t * alpha)
                        if want_alpha != 0:
                            behind = behind_scratch[p]
                            d_alpha = _grad_alpha(g_rgb, grad_alpha_out[p], color, behind, t, transmittance[p],
                                                  one_minus)
                            behind_scratch[p] = color * alpha + behind * one_minus
                            if raw < _ALPHA_MAX:
                                g_opacity += d_alpha * raw / opacity  # dalpha/do = exp(power)
                                g_mean = g_mean + wp.vec2(conic[0] * dx + conic[1] * dy,
                                                          conic[1] * dx + conic[2] * dy) * (d_alpha * raw)
                                g_conic = g_conic + wp.vec3(-0.5 * dx * dx, -dx * dy, -0.5 * dy * dy) * (d_alpha * raw)
        if hit != 0:
            if want_alpha != 0:
                wp.atomic_add(grad_means2d, g, g_mean)
                wp.atomic_add(grad_conics, g, g_conic)
                wp.atomic_add(grad_opacities, g, g_opacity)
            if want_colors != 0:
                wp.atomic_add(grad_colors, g, g_color)


@wp.kernel
def backward_pixels(tile_order: wp.array(dtype=wp.int32), first: int, step: int,  # tiles of this launch
                    tiles_x: int, width: int, height: int,
                    tile_start: wp.array(dtype=wp.int32), ids: wp.array(dtype=wp.int32),
                    boxes: wp.array(dtype=wp.vec4i), means2d: wp.array(dtype=wp.vec2),
                    conics: wp.array(dtype=wp.vec3), colors: wp.array(dtype=Any), opacities: wp.array(dtype=float),
                    background: wp.array(dtype=Any), transmittance: wp.array(dtype=float),
                    last: wp.array(dtype=wp.int32), grad_rgb: wp.array(dtype=Any),
                    grad_alpha_out: wp.array(dtype=float),
                    t_scratch: wp.array(dtype=float), behind_scratch: wp.array(dtype=Any),  # unused (same signature)
                    row_last: wp.array(dtype=wp.int32),  # unused
                    want_colors: int, want_alpha: int,
                    grad_means2d: wp.array(dtype=wp.vec2), grad_conics: wp.array(dtype=wp.vec3),
                    grad_colors: wp.array(dtype=Any), grad_opacities: wp.array(dtype=float)):
    # The derivation is that of backward_tiles, walked per pixel.
    txy = _pixel_of_thread(wp.tid(), tile_order, first, step, tiles_x)
    tile, x, y = txy[0], txy[1], txy[2]
    if x >= width or y >= height:
        return
    p = y * width + x
    t_final = transmittance[p]
    t = t_final
    behind = background[0]
    g_rgb = grad_rgb[p]
    g_alpha = grad_alpha_out[p]
    start = tile_start[tile]
    end = last[p]
    for j in range(start, end):
        k = end - 1 - (j - start)
        g = ids[k]
        box = boxes[g]
        if x >= box[0] and x <= box[2] and y >= box[1] and y <= box[3]:
            mean = means2d[g]
            conic = conics[g]
            dx = float(x) - mean[0]
            dy = float(y) - mean[1]
            opacity = opacities[g]
            raw = _raw_alpha(dx, dy, conic, opacity)
            alpha = wp.min(_ALPHA_MAX, raw)
            if alpha >= _ALPHA_MIN:
                one_minus = 1.0 - alpha
                t = t / one_minus
                if want_colors != 0:
                    wp.atomic_add(grad_colors, g, g_rgb * (t * alpha))
                if want_alpha != 0:
                    color = colors[g]
                    d_alpha = _grad_alpha(g_rgb, g_alpha, color, behind, t, t_final, one_minus)
                    behind = color * alpha + behind * one_minus
                    if raw < _ALPHA_MAX:
                        wp.atomic_add(grad_opacities, g, d_alpha * raw / opacity)
                        wp.atomic_add(grad_means2d, g, wp.vec2(conic[0] * dx + conic[1] * dy,
                                                               conic[1] * dx + conic[2] * dy) * (d_alpha * raw))
                        wp.atomic_add(grad_conics, g,
                                      wp.vec3(-0.5 * dx * dx, -dx * dy, -0.5 * dy * dy) * (d_alpha * raw))


_COLOR_ARGS = ("colors", "background", "rgb", "grad_rgb", "behind_scratch", "grad_colors")  # the generic arrays
for _kernel in (forward_tiles, forward_pixels, backward_tiles, backward_pixels):
    for _vec in (wp.vec3, wp.vec4):  # RGB and RGBA: built together on first launch; other C when first used
        wp.overload(_kernel, {name: wp.array(dtype=_vec) for name in _COLOR_ARGS if name in _kernel.arg_indices})


def color_type(channels: int):
    """The Warp vector type of `channels` colour channels (vec3 and vec4 are the prebuilt overloads)."""
    return {3: wp.vec3, 4: wp.vec4}.get(channels) or wp.types.vector(channels, wp.float32)
