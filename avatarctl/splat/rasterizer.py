"""`rasterize`: screen-space Gaussians of B images -> B images, with the Warp kernels behind a
`torch.autograd.Function`.

Steps: (0) `Canvas` lays the B images out on one canvas (one image is its own); (1) `bin_gaussians` lists, for every
16x16 tile, the splats that may count in it, front to back (CPU: a bucket sort in Warp; CUDA: one torch.sort on the
key (tile id << 32 | depth bits)); (2) the forward kernel composites each tile and keeps per pixel the final
transmittance and the last contributor; (3) the backward kernel walks back from there, computing only the gradients
autograd asks for (`ctx.needs_input_grad`: frozen colours cost no colour gradient, frozen geometry no alpha
gradient).

Backends: "torch" is the dense twin (`_torch_impl`, any dtype, tiny scenes); "warp" picks the kernel variant by
device: the tile walk on CPU, the pixel walk on CUDA; "warp_tile" / "warp_pixel" force one (both run on either
device); "auto" = "warp". The Warp path computes in float32. On CPU the tiles are shared among
`torch.get_num_threads()` Python threads (Warp's CPU launch releases the GIL while the kernel runs; each runs one
launch on one core), so `torch.set_num_threads` sets the cores used by both torch and the kernels.
"""

from __future__ import annotations

import contextlib
import functools
import threading
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import torch

from avatarctl.splat._torch_impl import ALPHA_MIN, TILE, rasterize_torch
from avatarctl.splat.camera import SplatCamera
from avatarctl.splat.project import FOV_CLAMP, LOW_PASS, Projected, footprint, within_bounds

BACKENDS = ("auto", "warp", "warp_tile", "warp_pixel", "torch")


@dataclass(frozen=True)
class TileBins:
    """Which splats touch which tile, front to back."""

    ids: torch.Tensor  # [entries] int32 splat index, sorted by (tile, depth)
    tile_start: torch.Tensor  # [tiles + 1] int32: the splats of tile t are ids[tile_start[t]:tile_start[t + 1]]
    tile_order: torch.Tensor  # [tiles] int32 tile ids, most entries first (the order work is handed out in)
    boxes: torch.Tensor  # [G, 4] int32 (x0, y0, x1, y1) inclusive: the pixels a splat may count at (`reach`)
    tiles_x: int
    tiles_y: int


def reach(proj: Projected, opacities: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """[G, 4] int32 (x0, y0, x1, y1), inclusive: the splat's footprint (`project.footprint`) cut down to the box of
    its ellipse o exp(power) >= ALPHA_MIN, widened by a margin (0.05 in power, 1 px); empty (x0 > x1) where no pixel
    can count. Every pixel outside has alpha < ALPHA_MIN, so binning and compositing over it give the footprint's
    image with fewer tiles and rows to visit."""
    box = footprint(proj.means2d, proj.radii, width, height)
    con, m = proj.conics.detach(), proj.means2d.detach()
    det = con[:, 0] * con[:, 2] - con[:, 1] ** 2
    r2 = 2.0 * (torch.log(torch.clamp(opacities.detach() / ALPHA_MIN, min=1e-30)) + 0.05)  # d^T conic d <= r2
    ok = (det > 0) & (con[:, 0] > 0)
    det = torch.where(ok, det, torch.ones_like(det))
    ext = torch.sqrt(torch.clamp(r2[:, None] * torch.stack([con[:, 2], con[:, 0]], -1) / det[:, None], min=0))
    lo = torch.floor(torch.clamp(m - ext - 1.0, -1e6, 1e6)).to(torch.int32)  # [G, 2]
    hi = torch.ceil(torch.clamp(m + ext + 1.0, -1e6, 1e6)).to(torch.int32)
    tight = torch.cat([torch.maximum(box[:, :2], lo), torch.minimum(box[:, 2:], hi)], -1)
    tight = torch.where(ok[:, None], tight, box)
    tight = torch.where((r2 > 0)[:, None], tight, torch.tensor([0, 0, -1, -1], dtype=torch.int32, device=box.device))
    return within_bounds(tight, proj)


def project_and_reach(means: torch.Tensor,  # [B, G, 3] world, metres: the Gaussians seen by camera b
                      covars: torch.Tensor,  # [B, G, 3, 3] world covariance, metres^2
                      opacities: torch.Tensor,  # [B, G] in [0, 1]
                      cams: Sequence[SplatCamera], near: float = 0.01, low_pass: float = LOW_PASS) -> Projected:
    """`project.project_gaussians` and `reach` in one Warp kernel (`_warp_kernels.project_reach`, one launch per
    camera), for rendering without gradients (float32, no autograd): one launch where the pure-torch pair issues ~180
    small operations, the cost that bounds a single render on a GPU. Same numbers up to float rounding
    (`tests/test_splat.py`); fields [B, G, ...], and `reach` [B, G, 4] holds each image's boxes, so binning does not
    compute them again."""
    import warp as wp

    k = _kernels()
    B, G = means.shape[:2]
    assert means.shape == (B, G, 3) and covars.shape == (B, G, 3, 3) and opacities.shape == (B, G) and \
        len(cams) == B, f"project_and_reach: means {list(means.shape)}, covars {list(covars.shape)}, opacities " \
                        f"{list(opacities.shape)} for {len(cams)} cameras"
    dev = means.device
    f32 = [t.detach().to(device=dev, dtype=torch.float32).contiguous() for t in (means, covars, opacities)]
    means2d, conics = torch.empty(B, G, 2, device=dev), torch.empty(B, G, 3, device=dev)
    depths, radii = torch.empty(B, G, device=dev), torch.empty(B, G, dtype=torch.int32, device=dev)
    boxes = torch.empty(B, G, 4, dtype=torch.int32, device=dev)
    for b, cam in enumerate(cams if G else ()):
        K, R, T = (getattr(cam, n).to(device=dev, dtype=torch.float32).contiguous()[None] for n in ("K", "R", "T"))
        inputs = [wp.from_torch(f32[0][b], dtype=wp.vec3), wp.from_torch(f32[1][b], dtype=wp.mat33),
                  wp.from_torch(f32[2][b]), wp.from_torch(K, dtype=wp.mat33), wp.from_torch(R, dtype=wp.mat33),
                  wp.from_torch(T, dtype=wp.vec3), int(cam.width), int(cam.height), float(near), float(low_pass),
                  FOV_CLAMP - 1.0]
        outputs = [wp.from_torch(means2d[b], dtype=wp.vec2), wp.from_torch(conics[b], dtype=wp.vec3),
                   wp.from_torch(depths[b]), wp.from_torch(radii[b]), wp.from_torch(boxes[b], dtype=wp.vec4i)]
        with torch_stream(dev):
            wp.launch(k.project_reach, dim=G, inputs=inputs + outputs, device=str(dev))
    return Projected(means2d=means2d, conics=conics, depths=depths, radii=radii, reach=boxes)


@dataclass(frozen=True)
class Canvas:
    """B images laid out on one canvas, so that one binning and one set of launches composite them all (what
    bounds small images on a GPU is the number of launches and synchronisations, not the pixels): image b's rows
    start at canvas row tops[b], a multiple of the tile (no tile holds two images), its columns at 0; every splat is
    confined to its image's window (`Projected.bounds`). One image is its own canvas (no bounds, no padding rows)."""

    proj: Projected  # [B * G] rows: means2d shifted down to the image's rows, bounds set (None for one image)
    width: int  # the widest image's
    height: int  # tops[-1]
    tops: tuple[int, ...]  # [B + 1] first canvas row of each image; tops[-1] = the canvas height
    sizes: tuple[tuple[int, int], ...]  # [B] (width, height) of each image

    @staticmethod
    def of(proj: Projected, sizes: Sequence[tuple[int, int]]) -> "Canvas":
        """The canvas of `proj` ([B, G, ...], `project.project_gaussians`) for images of `sizes` [(width, height)]."""
        B, G = proj.means2d.shape[:2]
        assert len(sizes) == B, f"Canvas: {len(sizes)} sizes for means2d {list(proj.means2d.shape)}"
        sizes = tuple((int(w), int(h)) for w, h in sizes)
        reach_ = proj.reach
        if B == 1:
            flat = Projected(means2d=proj.means2d[0], conics=proj.conics[0], depths=proj.depths[0],
                             radii=proj.radii[0], reach=None if reach_ is None else reach_[0])
            return Canvas(proj=flat, width=sizes[0][0], height=sizes[0][1], tops=(0, sizes[0][1]), sizes=sizes)
        tops = [0]
        for _, h in sizes:
            tops.append(tops[-1] + -(-h // TILE) * TILE)
        dev = proj.means2d.device
        top = torch.tensor(tops[:-1], dtype=proj.means2d.dtype, device=dev)  # [B]
        shift = torch.stack([torch.zeros_like(top), top], -1)[:, None, :]  # [B, 1, 2]
        bounds = torch.tensor([[0, t, w - 1, t + h - 1] for t, (w, h) in zip(tops, sizes)], dtype=torch.int32,
                              device=dev)  # [B, 4]
        if reach_ is not None:  # each image's boxes, inside its window: moved down with it (empty ones stay empty)
            rows = torch.tensor(tops[:-1], dtype=torch.int32, device=dev)
            reach_ = (reach_ + torch.stack([torch.zeros_like(rows), rows] * 2, -1)[:, None, :]).reshape(B * G, 4)
        flat = Projected(means2d=(proj.means2d + shift).reshape(B * G, 2), conics=proj.conics.reshape(B * G, 3),
                         depths=proj.depths.reshape(B * G), radii=proj.radii.reshape(B * G),
                         bounds=bounds[:, None, :].expand(B, G, 4).reshape(B * G, 4), reach=reach_)
        return Canvas(proj=flat, width=max(w for w, _ in sizes), height=tops[-1], tops=tuple(tops), sizes=sizes)

    def images(self, canvas: torch.Tensor):  # [height, width, ...] -> [B, H, W, ...] or [[H_b, W_b, ...]]
        """The B images cut from a canvas-sized tensor: one tensor [B, H, W, ...] (a view) when they all have one
        size, else a list of views [H_b, W_b, ...]; image b is `[b]` of either."""
        if len(set(self.sizes)) == 1:
            (w, h), B = self.sizes[0], len(self.sizes)
            return canvas.reshape(B, self.height // B, *canvas.shape[1:])[:, :h, :w]
        return [canvas[t:t + h, :w] for t, (w, h) in zip(self.tops, self.sizes)]


def bin_gaussians(proj: Projected, opacities: torch.Tensor, width: int, height: int) -> TileBins:
    """One entry per (splat, tile its `reach` box touches), sorted by tile, then depth, then splat index. On the CPU a
    bucket sort in Warp (`_bin_buckets`), on CUDA one torch.sort of (tile << 32 | depth bits) keys (`_bin_keys`)."""
    boxes = reach(proj, opacities, width, height) if proj.reach is None else proj.reach  # [G, 4]
    tiles_x, tiles_y = -(-width // TILE), -(-height // TILE)
    bin_ = _bin_buckets if boxes.device.type == "cpu" else _bin_keys
    ids, counts = bin_(boxes, proj.depths.detach(), tiles_x, tiles_y)
    tile_start = torch.cat([counts.new_zeros(1), torch.cumsum(counts, 0)]).to(torch.int32)
    tile_order = torch.argsort(counts, descending=True, stable=True).to(torch.int32)
    return TileBins(ids=ids, tile_start=tile_start, tile_order=tile_order, boxes=boxes, tiles_x=tiles_x,
                    tiles_y=tiles_y)


def _bin_keys(boxes: torch.Tensor, depths: torch.Tensor, tiles_x: int, tiles_y: int):
    """boxes [G, 4], depths [G] -> (ids [entries] int32, counts [tiles]): one entry per (splat, tile), sorted. The
    entries are listed by two Warp kernels (`count_entries`, `list_entries`: a dozen launches where torch took ~40,
    what a single render on a GPU pays for), then one stable torch.sort of the keys (tile << 32 | depth bits)."""
    import warp as wp

    k = _kernels()
    device, G = boxes.device, boxes.shape[0]
    box = wp.from_torch(boxes.contiguous(), dtype=wp.vec4i)
    counts = torch.empty(G, dtype=torch.int32, device=device)
    with torch_stream(device):
        if G:
            wp.launch(k.count_entries, dim=G, inputs=[box, wp.from_torch(counts)], device=str(device))
        ends = torch.cumsum(counts, 0, dtype=torch.int32)
        total = int(ends[-1]) if G else 0
        tile = torch.empty(total, dtype=torch.int32, device=device)
        g = torch.empty(total, dtype=torch.int32, device=device)
        if total:
            wp.launch(k.list_entries, dim=G, inputs=[box, tiles_x, wp.from_torch(ends), wp.from_torch(tile),
                                                     wp.from_torch(g)], device=str(device))
    depth_bits = depths.float().contiguous().view(torch.int32).long()  # monotone for depth > 0
    _, order = torch.sort((tile.long() << 32) | depth_bits[g.long()], stable=True)
    return g[order], torch.bincount(tile, minlength=tiles_x * tiles_y)


def _bin_buckets(boxes: torch.Tensor, depths: torch.Tensor, tiles_x: int, tiles_y: int):
    """`_bin_keys`' result by a bucket sort (Warp, CPU): count per tile, then append the splats in depth order."""
    import warp as wp

    k = _kernels()
    G = boxes.shape[0]
    counts = torch.zeros(tiles_x * tiles_y, dtype=torch.int32, device=boxes.device)
    visible = torch.nonzero((boxes[:, 0] <= boxes[:, 2]) & (boxes[:, 1] <= boxes[:, 3])).squeeze(-1)
    if visible.shape[0] == 0:
        return torch.zeros(0, dtype=torch.int32, device=boxes.device), counts
    box = wp.from_torch(boxes.contiguous(), dtype=wp.vec4i)
    wp.launch(k.count_tiles, dim=G, inputs=[box, tiles_x, wp.from_torch(counts)], device=str(boxes.device))
    cursor = (torch.cumsum(counts, 0) - counts).to(torch.int32)
    m = visible.shape[0]  # the splats front to back: Warp's radix sort (stable, ~6x torch.argsort on the CPU)
    keys, order = torch.empty(2 * m, device=boxes.device), torch.empty(2 * m, dtype=torch.int32, device=boxes.device)
    keys[:m], order[:m] = depths[visible], visible
    wp.utils.radix_sort_pairs(wp.from_torch(keys), wp.from_torch(order), m)
    order = order[:m]
    ids = torch.empty(int(counts.sum()), dtype=torch.int32, device=boxes.device)
    wp.launch(k.fill_tiles, dim=1, inputs=[wp.from_torch(order), box, tiles_x, wp.from_torch(cursor),
                                           wp.from_torch(ids)], device=str(boxes.device))
    return ids, counts


def rasterize(proj: Projected,  # fields [B, G, ...]: `project.project_gaussians`
              colors: torch.Tensor,  # [B, G, C]
              opacities: torch.Tensor,  # [B, G] in [0, 1]
              sizes: Sequence[tuple[int, int]],  # [B] (width, height) of each image
              background: torch.Tensor,  # [C]
              backend: str = "auto"):
    """Alpha-composite the splats of B images front to back (3DGS; the rules are in `_torch_impl`'s docstring), all
    on one `Canvas`: one binning and one set of kernel launches whatever B.

    -> (rgb, alpha) as `Canvas.images` cuts them: rgb [B, H, W, C] over the background and alpha [B, H, W] when the
    images have one size, else lists of [H_b, W_b, C] and [H_b, W_b]. The same images as one call per image up to
    the float rounding of the shifted pixel rows. Differentiable w.r.t. proj.means2d, proj.conics, colors and
    opacities (not the background); the Warp backward computes only the gradients required. `backend`: see the
    module docstring.
    """
    B, G = proj.means2d.shape[:2]
    assert colors.ndim == 3 and colors.shape[:2] == (B, G) and opacities.shape == (B, G), \
        f"rasterize: colors {list(colors.shape)}, opacities {list(opacities.shape)} for means2d " \
        f"{list(proj.means2d.shape)} (expected [{B}, {G}, C] and [{B}, {G}])"
    canvas = Canvas.of(proj, sizes)
    rgb, alpha = _composite(canvas.proj, colors.reshape(B * G, colors.shape[2]), opacities.reshape(B * G), canvas.width,
                            canvas.height, background, backend)
    return canvas.images(rgb), canvas.images(alpha)


def _composite(proj: Projected,  # fields [G, ...]: one canvas (`Canvas.proj`)
               colors: torch.Tensor,  # [G, C]
               opacities: torch.Tensor,  # [G] in [0, 1]
               width: int, height: int, background: torch.Tensor,  # [C]
               backend: str) -> tuple[torch.Tensor, torch.Tensor]:
    """One canvas composited -> rgb [height, width, C], alpha [height, width]: the twin, or binning and the Warp
    kernels."""
    G = proj.means2d.shape[0]
    assert proj.means2d.shape == (G, 2), f"means2d: expected [G, 2], got {list(proj.means2d.shape)}"
    assert proj.conics.shape == (G, 3), f"conics: expected [{G}, 3], got {list(proj.conics.shape)}"
    assert proj.depths.shape == (G,) and proj.radii.shape == (G,), \
        f"depths, radii: expected [{G}], got {list(proj.depths.shape)}, {list(proj.radii.shape)}"
    assert colors.ndim == 2 and colors.shape[0] == G, f"colors: expected [{G}, C], got {list(colors.shape)}"
    assert opacities.shape == (G,), f"opacities: expected [{G}], got {list(opacities.shape)}"
    assert background.shape == colors.shape[1:], \
        f"background: expected [{colors.shape[1]}] (the colour channels), got {list(background.shape)}"
    if backend not in BACKENDS:
        raise ValueError(f"rasterize: unknown backend {backend!r}; expected one of {', '.join(BACKENDS)}")
    if backend == "torch":
        return rasterize_torch(proj, colors, opacities, width, height, background)
    tensors = (proj.means2d, proj.conics, colors, opacities, background)
    if any(t.dtype != torch.float32 for t in tensors):
        raise ValueError("rasterize: the Warp backend computes in float32, got "
                         f"{sorted({str(t.dtype) for t in tensors})} (use backend='torch' for float64)")
    on_cuda = proj.means2d.device.type == "cuda"
    variant = {"warp_tile": "tiles", "warp_pixel": "pixels"}.get(backend, "pixels" if on_cuda else "tiles")
    bins = bin_gaussians(proj, opacities, width, height)
    return _RasterizeWarp.apply(proj.means2d, proj.conics, colors, opacities, background, bins, width, height,
                                variant)


def _kernels():
    """The Warp kernel module, imported on first use; Warp initialised (it builds the kernels on first launch)."""
    from avatarctl.device import init_warp

    init_warp()
    from avatarctl.splat import _warp_kernels

    return _warp_kernels


def torch_stream(device: torch.device):
    """The context Warp launches on `device` run in: torch's current CUDA stream (so they order with torch's own
    operations), nothing on the CPU."""
    import warp as wp

    return wp.ScopedStream(wp.stream_from_torch(device)) if device.type == "cuda" else contextlib.nullcontext()


@functools.lru_cache(maxsize=None)
def _pool(workers: int) -> ThreadPoolExecutor:
    return ThreadPoolExecutor(max_workers=workers, thread_name_prefix="splat")


_BUILT: set[tuple] = set()  # (kernel, colour type, device) launched once: Warp has built it
_BUILD_LOCK = threading.Lock()


def _launch(kernel, bins: TileBins, per_tile: int, jobs: int, args_of_job, channels: int,
            device: torch.device) -> None:
    """Launch `kernel` over the tiles as `jobs` launches (job j: tile_order[j], tile_order[j + jobs], ...),
    concurrently from a thread pool on CPU. `args_of_job(j)` -> the kernel's inputs after (tile_order, first, step);
    `channels` picks the kernel's overload (the colour vector type)."""
    import warp as wp

    tiles = bins.tiles_x * bins.tiles_y
    tile_order = wp.from_torch(bins.tile_order)

    def one(j: int) -> None:
        n = len(range(j, tiles, jobs))
        if n:
            wp.launch(kernel, dim=n * per_tile, inputs=[tile_order, j, jobs, *args_of_job(j)], device=str(device))

    if device.type == "cuda":
        with torch_stream(device):
            one(0)
        return
    key = (kernel.key, channels, str(device))
    if jobs == 1 or key not in _BUILT:
        with _BUILD_LOCK:  # the first launch builds the module: not from two threads at once
            for j in range(jobs):
                one(j)
            _BUILT.add(key)
        return
    futures = [_pool(jobs - 1).submit(one, j) for j in range(1, jobs)]
    one(0)
    for f in futures:
        f.result()


def _jobs(device: torch.device) -> int:
    return 1 if device.type == "cuda" else max(1, torch.get_num_threads())


class _RasterizeWarp(torch.autograd.Function):
    """Autograd glue of the Warp kernels: tensors shared with Warp without copies (wp.from_torch)."""

    @staticmethod
    def forward(ctx, means2d, conics, colors, opacities, background, bins: TileBins, width: int, height: int,
                variant: str):
        import warp as wp

        k = _kernels()
        device = means2d.device
        C = colors.shape[1]
        vec = k.color_type(C)
        P = width * height
        rgb = torch.empty(P, C, device=device)
        trans = torch.ones(P, device=device)
        last = torch.zeros(P, dtype=torch.int32, device=device)
        inputs = _inputs(bins, width, height, means2d, conics, colors, opacities, background, vec)
        if bins.ids.shape[0] == 0:  # nothing visible: no launch (a kernel needs at least one entry to index)
            rgb[:] = background
        else:
            rows = torch.empty(bins.tiles_x * bins.tiles_y * TILE, dtype=torch.int32, device=device)  # scratch
            outs = [wp.from_torch(rgb, dtype=vec), wp.from_torch(trans), wp.from_torch(last), wp.from_torch(rows)]
            kernel = k.forward_tiles if variant == "tiles" else k.forward_pixels
            per_tile = 1 if variant == "tiles" else TILE * TILE
            _launch(kernel, bins, per_tile, _jobs(device), lambda j: inputs + outs, C, device)
        ctx.save_for_backward(means2d, conics, colors, opacities, background, trans, last)
        ctx.bins, ctx.size, ctx.variant = bins, (width, height), variant
        return rgb.reshape(height, width, C), (1 - trans).reshape(height, width)

    @staticmethod
    def backward(ctx, grad_rgb, grad_alpha):
        import warp as wp

        k = _kernels()
        means2d, conics, colors, opacities, background, trans, last = ctx.saved_tensors
        bins, (width, height) = ctx.bins, ctx.size
        device, (G, C), P = means2d.device, colors.shape, width * height
        jobs = _jobs(device)
        # what is required: the colours' gradient, and the ones through alpha (means2d, conics, opacities share it)
        want = (ctx.needs_input_grad[2], any(ctx.needs_input_grad[i] for i in (0, 1, 3)))
        computed = (want[1], want[1], want[0], want[1])  # of means2d, conics, colors, opacities
        grads = [torch.zeros(jobs, G if c else 1, n, device=device)  # per job: CPU atomics are plain adds; an output
                 for c, n in zip(computed, (2, 3, C, 1))]  # not computed: one row, never written
        if bins.ids.shape[0] > 0:
            vec = k.color_type(C)
            inputs = _inputs(bins, width, height, means2d, conics, colors, opacities, background, vec)
            grad_rgb = grad_rgb.float().contiguous().reshape(P, C)
            grad_alpha = grad_alpha.float().contiguous().reshape(P)
            scratch = [wp.from_torch(torch.empty(P, device=device)),
                       wp.from_torch(torch.empty(P, C, device=device), dtype=vec),
                       wp.from_torch(torch.empty(bins.tiles_x * bins.tiles_y * TILE, dtype=torch.int32, device=device))]
            state = [wp.from_torch(trans), wp.from_torch(last), wp.from_torch(grad_rgb, dtype=vec),
                     wp.from_torch(grad_alpha)]
            outs = [[int(want[0]), int(want[1]), wp.from_torch(grads[0][j], dtype=wp.vec2),
                     wp.from_torch(grads[1][j], dtype=wp.vec3), wp.from_torch(grads[2][j], dtype=vec),
                     wp.from_torch(grads[3][j].reshape(-1))] for j in range(jobs)]
            kernel = k.backward_tiles if ctx.variant == "tiles" else k.backward_pixels
            per_tile = 1 if ctx.variant == "tiles" else TILE * TILE
            _launch(kernel, bins, per_tile, jobs, lambda j: inputs + state + scratch + outs[j], C, device)
        g_means, g_conics, g_colors, g_opac = (g.sum(0) if ctx.needs_input_grad[i] else None
                                               for i, g in zip((0, 1, 2, 3), grads))
        return g_means, g_conics, g_colors, None if g_opac is None else g_opac.reshape(G), None, None, None, None, None


def _inputs(bins: TileBins, width, height, means2d, conics, colors, opacities, background, vec) -> list:
    """The kernels' shared inputs after (tile_order, first, step)."""
    import warp as wp

    def view(t: torch.Tensor, dtype=None):
        return wp.from_torch(t.detach().contiguous(), dtype=dtype, requires_grad=False)

    return [bins.tiles_x, width, height, view(bins.tile_start), view(bins.ids), view(bins.boxes, wp.vec4i),
            view(means2d, wp.vec2), view(conics, wp.vec3), view(colors, vec), view(opacities),
            view(background.reshape(1, -1), vec)]
