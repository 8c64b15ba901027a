"""avatarctl.splat: projection by hand, the Warp kernels (tile walk and pixel walk) against the pure-PyTorch twin,
forward and backward, the twin against finite differences, the compositing cut-offs, empty scenes, both CPU cores,
the entry point `rasterization` (single and batch, equal and unequal sizes, its meta record, the gradients it
computes and skips) and the benchmark at toy scale. `gpu` tests repeat the parity on CUDA."""

from __future__ import annotations

import ast
import importlib.util
from pathlib import Path

import numpy as np
import pytest
import torch

from avatarctl.geometry.cameras import Camera, look_at
from avatarctl.splat import SplatCamera, SplatMeta, rasterization
from avatarctl.splat._torch_impl import rasterize_torch
from avatarctl.splat.project import Projected, project_gaussians
from avatarctl.splat.rasterizer import Canvas, project_and_reach, rasterize, reach

WARP = ["warp_tile", "warp_pixel"]
W, H = 37, 29  # not a multiple of the 16 px tile


def _camera(width: int = W, height: int = H, f: float = 30.0, dtype=torch.float32) -> SplatCamera:
    K = torch.tensor([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]], dtype=dtype)
    return SplatCamera(K=K, R=torch.eye(3, dtype=dtype), T=torch.zeros(3, dtype=dtype), width=width, height=height)


def _scene(seed: int, G: int = 60, channels: int = 3, dtype=torch.float32):
    """Random Gaussians 1.2-3 m in front of `_camera`, straddling tiles and the image border; 4 behind the camera,
    a third nearly opaque (pixels terminate early); covariances from non-orthonormal maps A A^T."""
    gen = torch.Generator().manual_seed(seed)
    z = 1.2 + 1.8 * torch.rand(G, generator=gen)
    xy = (torch.rand(G, 2, generator=gen) - 0.5) * z[:, None] * torch.tensor([1.5, 1.2])
    means = torch.cat([xy, z[:, None]], -1)
    means[:4, 2] = -means[:4, 2]
    A = torch.randn(G, 3, 3, generator=gen) * (0.02 + 0.15 * torch.rand(G, 1, 1, generator=gen))
    covars = A @ A.transpose(-1, -2)
    colors = torch.rand(G, channels, generator=gen)
    opacities = torch.rand(G, generator=gen)
    opaque = slice(G // 3, 2 * G // 3)
    opacities[opaque] = 0.995  # above ALPHA_MAX: clamped, no gradient through alpha
    means[opaque, :2] *= 0.3  # piled up in the middle: pixels end early
    return means.to(dtype), covars.to(dtype), colors.to(dtype), opacities.to(dtype)


def _project(means, covars, cam: SplatCamera, **kw) -> Projected:
    """One camera's projection as one canvas: fields [G, ...]."""
    return Canvas.of(project_gaussians(means[None], covars[None], [cam], **kw), [(cam.width, cam.height)]).proj


def _raster(proj: Projected, colors, opacities, width, height, background, backend: str = "auto"):
    """`rasterize` of one image given as a canvas [G] -> rgb [H, W, C], alpha [H, W]."""
    batch = Projected(means2d=proj.means2d[None], conics=proj.conics[None], depths=proj.depths[None],
                      radii=proj.radii[None])
    rgb, alpha = rasterize(batch, colors[None], opacities[None], [(width, height)], background, backend)
    return rgb[0], alpha[0]


def _leaves(proj: Projected, colors, opacities):
    """Fresh leaves for (means2d, conics, colors, opacities) and the Projected that uses them."""
    m2, con = proj.means2d.detach().requires_grad_(), proj.conics.detach().requires_grad_()
    c, o = colors.detach().requires_grad_(), opacities.detach().requires_grad_()
    return [m2, con, c, o], Projected(means2d=m2, conics=con, depths=proj.depths.detach(), radii=proj.radii)


def _grads(backend: str, proj: Projected, colors, opacities, background, seed: int = 0):
    leaves, p = _leaves(proj, colors, opacities)
    if backend == "twin":
        rgb, alpha = rasterize_torch(p, leaves[2], leaves[3], W, H, background)
    else:
        rgb, alpha = _raster(p, leaves[2], leaves[3], W, H, background, backend=backend)
    gen = torch.Generator().manual_seed(seed)
    g_rgb, g_alpha = torch.randn(rgb.shape, generator=gen), torch.randn(alpha.shape, generator=gen)
    torch.autograd.backward([rgb, alpha], [g_rgb.to(rgb), g_alpha.to(alpha)])
    return [t.grad for t in leaves]


# projection ----------------------------------------------------------------------------------------------------

def test_projection_by_hand():
    K = torch.tensor([[100.0, 0.0, 50.0], [0.0, 120.0, 40.0], [0.0, 0.0, 1.0]])
    cam = SplatCamera(K=K, R=torch.eye(3), T=torch.zeros(3), width=100, height=80)
    s = 0.05  # isotropic, metres
    means = torch.tensor([[0.0, 0.0, 2.0], [0.2, -0.1, 2.0], [0.0, 0.0, -1.0], [0.0, 0.0, 0.005]])
    proj = _project(means, (s * s) * torch.eye(3).expand(4, 3, 3), cam)
    assert torch.allclose(proj.means2d[:2], torch.tensor([[50.0, 40.0], [60.0, 34.0]]))
    var = torch.tensor([(100 * s / 2) ** 2 + 0.3, (120 * s / 2) ** 2 + 0.3])  # on the axis: J = diag(f / z)
    assert torch.allclose(proj.conics[0], torch.tensor([1 / var[0], 0.0, 1 / var[1]]))
    assert proj.radii[0] == int(np.ceil(3 * float(var.max()) ** 0.5))
    assert proj.radii.dtype == torch.int32 and proj.radii[2] == 0 and proj.radii[3] == 0  # behind, inside near
    assert torch.allclose(proj.depths, means[:, 2])
    far_off = _project(torch.tensor([[5.0, 0.0, 2.0]]), 1e-4 * torch.eye(3)[None], cam)
    assert far_off.radii[0] == 0  # footprint misses the image
    # the low-pass is the caller's: 0.1 px^2 instead of 3DGS's 0.3 on the same Gaussians
    sharp = _project(means, (s * s) * torch.eye(3).expand(4, 3, 3), cam, low_pass=0.1)
    var = torch.tensor([(100 * s / 2) ** 2 + 0.1, (120 * s / 2) ** 2 + 0.1])
    assert torch.allclose(sharp.conics[0], torch.tensor([1 / var[0], 0.0, 1 / var[1]]))


def test_projection_agrees_with_the_calibrated_camera_and_crop():
    R, T = look_at(np.array([2.0, -2.5, 1.2]), np.array([0.0, 0.0, 0.9]))
    cam = Camera(name="c", K=np.array([[300.0, 0, 120], [0, 310.0, 90], [0, 0, 1]]), R=R, T=T, width=240,
                 height=180)
    X = np.random.default_rng(0).uniform(-0.3, 0.3, (10, 3)) + [0.0, 0.0, 0.9]
    sc = SplatCamera.from_camera(cam)
    proj = _project(torch.tensor(X, dtype=torch.float32), 1e-4 * torch.eye(3).expand(10, 3, 3), sc)
    assert np.allclose(proj.means2d.numpy(), cam.project(X), atol=1e-3)
    crop = _project(torch.tensor(X, dtype=torch.float32), 1e-4 * torch.eye(3).expand(10, 3, 3),
                             sc.crop(30, 20, 100, 90))
    assert torch.allclose(crop.means2d, proj.means2d - torch.tensor([30.0, 20.0]), atol=1e-4)
    with pytest.raises(ValueError, match="distortion"):
        SplatCamera.from_camera(Camera(name="d", K=cam.K, R=R, T=T, width=240, height=180,
                                       dist=np.array([0.1, 0, 0, 0, 0])))


# compositing ---------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("backend", ["torch", *WARP])
def test_compositing_rule_by_hand(backend):
    """Three splats centred on pixel (5, 5), alpha 0.99, 0.98, 0.6 front to back: T goes 1 -> 0.01 -> 2e-4, and the
    third would take it below 1e-4, so it ends the pixel unadded."""
    colors = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 1.0]])
    proj = Projected(means2d=torch.full((3, 2), 5.0), conics=torch.full((3, 3), 1e-3) * torch.tensor([1, 0, 1]),
                     depths=torch.tensor([3.0, 1.0, 2.0]), radii=torch.full((3,), 3, dtype=torch.int32))
    opacities = torch.tensor([0.6, 0.99, 0.98])
    bg = torch.tensor([0.0, 0.0, 1.0])
    rgb, alpha = _raster(proj, colors[[2, 0, 1]], opacities, 12, 11, bg, backend=backend)
    expect = torch.tensor([0.99, 0.01 * 0.98, 2e-4])
    assert torch.allclose(rgb[5, 5], expect, atol=1e-6) and abs(float(alpha[5, 5]) - (1 - 2e-4)) < 1e-6
    assert torch.equal(rgb[5, 9], bg) and alpha[5, 9] == 0  # outside the footprint (radius 3)


@pytest.mark.parametrize("backend", WARP)
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_warp_forward_matches_the_twin(backend, seed):
    means, covars, colors, opacities = _scene(seed)
    proj = _project(means, covars, _camera())
    bg = torch.tensor([0.2, 0.5, 0.9])
    assert (proj.radii == 0).sum() >= 4 and (proj.radii > 16).any()  # culled ones, and ones wider than a tile
    ref_rgb, ref_alpha = rasterize_torch(proj, colors, opacities, W, H, bg)
    rgb, alpha = _raster(proj, colors, opacities, W, H, bg, backend=backend)
    assert float(ref_alpha.max()) > 1 - 1e-3  # some pixels end early (T < 1e-3)
    assert (rgb - ref_rgb).abs().max() < 1e-5 and (alpha - ref_alpha).abs().max() < 1e-5


@pytest.mark.parametrize("backend", WARP)
@pytest.mark.parametrize("seed", [0, 3])
def test_warp_backward_matches_twin_autograd(backend, seed):
    means, covars, colors, opacities = _scene(seed)
    proj = _project(means, covars, _camera())
    bg = torch.tensor([0.2, 0.5, 0.9])
    ref = _grads("twin", proj, colors, opacities, bg)
    got = _grads(backend, proj, colors, opacities, bg)
    for name, g, r in zip(["means2d", "conics", "colors", "opacities"], got, ref):
        err = float((g - r).abs().max() / r.abs().max())
        assert err < 1e-4, f"{name}: relative error {err:.2e}"


def test_rgba_channels():
    means, covars, colors, opacities = _scene(4, channels=4)
    proj = _project(means, covars, _camera())
    bg = torch.tensor([0.2, 0.5, 0.9, 0.0])
    ref = rasterize_torch(proj, colors, opacities, W, H, bg)
    got = _raster(proj, colors, opacities, W, H, bg)
    assert got[0].shape == (H, W, 4) and (got[0] - ref[0]).abs().max() < 1e-5
    for g, r in zip(_grads("warp", proj, colors, opacities, bg), _grads("twin", proj, colors, opacities, bg)):
        assert float((g - r).abs().max() / r.abs().max()) < 1e-4


def _key_sort_against_buckets(device: str) -> None:
    from avatarctl.splat.rasterizer import _bin_buckets, _bin_keys, reach

    means, covars, colors, opacities = _scene(8, G=300)
    means[:20, 2] = means[20:40, 2]  # equal depths: ties go by splat index
    proj = _project(means, covars, _camera())
    boxes = reach(proj, opacities, W, H)
    keys = [t.cpu() for t in _bin_keys(boxes.to(device), proj.depths.to(device), 3, 2)]
    buckets = _bin_buckets(boxes, proj.depths, 3, 2)
    assert keys[0].shape[0] > 300 and torch.equal(keys[0], buckets[0]) and torch.equal(keys[1], buckets[1].long())
    none = _bin_keys(torch.tensor([[0, 0, -1, -1]], dtype=torch.int32, device=device), proj.depths[:1].to(device), 3, 2)
    assert none[0].shape == (0,) and int(none[1].sum()) == 0


def test_bucket_binning_matches_the_key_sort():
    """The CPU's bucket sort (Warp) and CUDA's key sort (entries listed in Warp, one torch.sort) give the same tile
    lists, depth ties included; a scene that touches no tile gives empty lists."""
    _key_sort_against_buckets("cpu")


@pytest.mark.gpu
def test_cuda_key_sort_matches_the_buckets():
    _key_sort_against_buckets("cuda")


def test_twin_gradients_match_finite_differences():
    """float64, through projection and compositing, cut-offs off (with them the footprint and 1/255 edges make the
    image jump where a splat crosses them)."""
    means, covars, colors, opacities = _scene(5, G=6, dtype=torch.float64)
    means = means.abs() + torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)  # all in front
    opacities = 0.2 + 0.6 * opacities  # below ALPHA_MAX
    cam = _camera(9, 7, f=8.0, dtype=torch.float64)
    bg = torch.tensor([0.3, 0.6, 0.1], dtype=torch.float64)

    def image(m, cv, c, o):
        proj = _project(m, cv, cam)
        rgb, alpha = rasterize_torch(proj, c, o, cam.width, cam.height, bg, cutoffs=False)
        return rgb, alpha

    inputs = [t.clone().requires_grad_() for t in (means, covars, colors, opacities)]
    assert torch.autograd.gradcheck(image, inputs, eps=1e-6, atol=1e-6, rtol=1e-4, fast_mode=True)


@pytest.mark.parametrize("backend", ["torch", *WARP])
def test_empty_scene_gives_the_background(backend):
    bg = torch.tensor([0.1, 0.2, 0.3])
    for G in (0, 3):  # nothing, or only Gaussians behind the camera
        means = torch.tensor([[0.0, 0.0, -2.0]]).repeat(G, 1)
        colors, opacities = torch.rand(G, 3, requires_grad=True), torch.rand(G, requires_grad=True)
        rgb, alpha, meta = rasterization(means, 0.01 * torch.eye(3).expand(G, 3, 3), colors, opacities, [_camera()],
                                         bg, backend=backend)
        assert torch.equal(rgb, bg.expand(1, H, W, 3)) and not alpha.any() and meta.radii.shape == (1, G)
        (rgb.sum() + alpha.sum()).backward()
        assert colors.grad is None or not colors.grad.any()


def test_two_threads_match_one():
    means, covars, colors, opacities = _scene(6)
    proj = _project(means, covars, _camera())
    bg = torch.tensor([0.2, 0.5, 0.9])
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = _raster(proj, colors, opacities, W, H, bg), _grads("warp", proj, colors, opacities, bg)
        torch.set_num_threads(2)
        two = _raster(proj, colors, opacities, W, H, bg), _grads("warp", proj, colors, opacities, bg)
    finally:
        torch.set_num_threads(threads)
    assert torch.equal(one[0][0], two[0][0]) and torch.equal(one[0][1], two[0][1])
    for a, b in zip(one[1], two[1]):  # per-thread gradient sums, added in another order
        assert float((a - b).abs().max() / b.abs().max()) < 1e-5


def test_rejects_bad_input():
    means, covars, colors, opacities = _scene(0)
    proj = _project(means, covars, _camera())
    with pytest.raises(AssertionError, match=r"rasterize: colors \[1, 5, 3\]"):
        _raster(proj, colors[:5], opacities, W, H, torch.zeros(3))
    with pytest.raises(ValueError, match="unknown backend"):
        _raster(proj, colors, opacities, W, H, torch.zeros(3), backend="cuda")
    with pytest.raises(ValueError, match="float32"):
        _raster(proj, colors.double(), opacities, W, H, torch.zeros(3))
    # the entry point: each input with or without the leading [B], the rest of its shape that of means
    cams, bg = [_camera(), _camera()], torch.zeros(3)
    with pytest.raises(AssertionError, match=r"colors: expected \[2, 60, 3\] or \[60, 3\] .*got \[5, 3\]"):
        rasterization(means, covars, colors[:5], opacities, cams, bg)
    with pytest.raises(AssertionError, match=r"opacities: expected 1 dims .* leading 2, got \[3, 60\]"):
        rasterization(means, covars, colors, opacities.expand(3, 60), cams, bg)
    with pytest.raises(AssertionError, match="no camera"):
        rasterization(means, covars, colors, opacities, [], bg)


def test_warp_is_imported_lazily():
    """No module of the library but the kernels' imports Warp (or the kernels) at module level: importing
    avatarctl.splat stays Warp-free, the kernels load on the first Warp rasterization."""
    import avatarctl.splat as splat

    for path in Path(splat.__file__).parent.glob("*.py"):
        if path.name == "_warp_kernels.py":
            continue
        top = [n for n in ast.parse(path.read_text()).body if isinstance(n, (ast.Import, ast.ImportFrom))]
        names = [a.name for n in top for a in n.names] + [n.module or "" for n in top if isinstance(n, ast.ImportFrom)]
        assert not [n for n in names if n.startswith("warp") or n.endswith("_warp_kernels")], path.name


def test_benchmark_runs_at_toy_scale():
    path = Path(__file__).resolve().parents[1] / "benchmarks" / "splat_bench.py"
    spec = importlib.util.spec_from_file_location("splat_bench", path)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    result = bench.run("cpu", sizes=((32, 300),), threads=(1,), repeats=1)
    (row,) = result["rows"]
    assert row["visible"] > 0 and row["forward_ms"] > 0 and "forward" in bench.table(result)


def _batch_scene(device: str = "cpu"):
    """Three images of different window sizes (not multiples of the tile) seeing three different Gaussian sets."""
    scenes = [_scene(s, G=50) for s in (0, 4, 5)]
    means, covars, colors, opacities = (torch.stack([sc[i] for sc in scenes]).to(device) for i in range(4))
    cams = [_camera(37, 29).to(device), _camera(20, 45, f=25.0).crop(-3, 4, 20, 45).to(device),
            _camera(33, 16).to(device)]
    return means, covars, colors, opacities, cams


def test_batched_projection_matches_one_camera_at_a_time():
    means, covars, _, _, cams = _batch_scene()
    batch = project_gaussians(means, covars, cams)
    for b, cam in enumerate(cams):
        one = project_gaussians(means[b:b + 1], covars[b:b + 1], [cam])
        for name in ("means2d", "conics", "depths"):
            assert torch.allclose(getattr(batch, name)[b], getattr(one, name)[0], atol=1e-5, rtol=1e-5), name
        assert torch.equal(batch.radii[b], one.radii[0])


def _batched_against_single(backend: str, device: str, cams=None):
    """(max |image difference|, max relative gradient difference) of one `rasterization` of the batch against one
    call per image on the same leaves."""
    means, covars, colors, opacities, batch_cams = _batch_scene(device)
    cams = batch_cams if cams is None else [c.to(device) for c in cams]
    bg = torch.tensor([0.2, 0.5, 0.9], device=device)
    gen = torch.Generator().manual_seed(0)
    weights = [torch.randn(c.height, c.width, 4, generator=gen).to(device) for c in cams]
    results = []
    for batched in (True, False):
        leaves = [t.detach().clone().requires_grad_() for t in (means, covars, colors, opacities)]
        if batched:
            rgb, alpha, _ = rasterization(*leaves, cams, bg, backend=backend)
            images = list(zip(rgb, alpha))
        else:
            images = [tuple(out[0] for out in rasterization(*(t[b] for t in leaves), [cams[b]], bg,
                                                            backend=backend)[:2]) for b in range(len(cams))]
        loss = sum((torch.cat([rgb, alpha[..., None]], -1) * w).sum() for (rgb, alpha), w in zip(images, weights))
        loss.backward()
        results.append((images, [t.grad for t in leaves]))
    (img_b, grad_b), (img_s, grad_s) = results
    assert [tuple(i[0].shape) for i in img_b] == [(c.height, c.width, 3) for c in cams]
    img = max(float((a - b).detach().abs().max()) for x, y in zip(img_b, img_s) for a, b in zip(x, y))
    grad = max(float((a - b).abs().max() / b.abs().max()) for a, b in zip(grad_b, grad_s))
    return img, grad


@pytest.mark.parametrize("sizes", ["unequal", "equal"])
@pytest.mark.parametrize("backend", ["torch", *WARP])
def test_batched_rendering_matches_one_image_at_a_time(backend, sizes):
    """Several images on one canvas (`rasterizer.Canvas`): the same images and gradients as one call per image (each
    splat kept inside its own image's window, even where it would reach into the next)."""
    cams = None if sizes == "unequal" else [_camera(37, 29), _camera(37, 29, f=25.0).crop(-3, 4, 37, 29),
                                            _camera(37, 29, f=35.0)]
    img, grad = _batched_against_single(backend, "cpu", cams)
    assert img < 1e-5 and grad < 1e-4


# the entry point ------------------------------------------------------------------------------------------------

_LAYOUTS = {  # name -> (scene indices per image, cameras): shared inputs have no leading [B]
    "single": lambda: [_camera()],
    "equal": lambda: [_camera(), _camera(37, 29, f=25.0).crop(-3, 4, 37, 29), _camera(37, 29, f=35.0)],
    "unequal": lambda: [_camera(), _camera(20, 45, f=25.0).crop(-3, 4, 20, 45), _camera(33, 16)],
}


def _entry_point(backend: str, cams, shared: bool, weights_seed: int = 0, frozen=()):
    """rasterization of `_scene`s (one per camera, or `_scene(0)` shared by all) -> (rgb, alpha, meta, grads of
    means, covars, colors, opacities (None where frozen)), after a weighted sum of the images is differentiated."""
    scenes = [_scene(s) for s in range(len(cams))]
    inputs = scenes[0] if shared else [torch.stack([sc[i] for sc in scenes]) for i in range(4)]
    leaves = [t.clone().requires_grad_(i not in frozen) for i, t in enumerate(inputs)]
    rgb, alpha, meta = rasterization(*leaves, cams, torch.tensor([0.2, 0.5, 0.9]), backend=backend)
    gen = torch.Generator().manual_seed(weights_seed)
    loss = sum((r * torch.randn(r.shape, generator=gen)).sum() + (a * torch.randn(a.shape, generator=gen)).sum()
               for r, a in zip(rgb, alpha))
    if meta.means2d.requires_grad:
        meta.means2d.retain_grad()
    loss.backward()
    return rgb, alpha, meta, [t.grad for t in leaves]


@pytest.mark.parametrize("shared", [False, True])
@pytest.mark.parametrize("layout", list(_LAYOUTS))
@pytest.mark.parametrize("backend", WARP)
def test_entry_point_matches_the_twin(backend, layout, shared):
    """`rasterization` through the Warp kernels = through the pure-torch twin: images, the meta record and the
    gradients of all four inputs, for one image and for batches of equal and unequal sizes, each input per image
    ([B, G, ...]) or shared by all ([G, ...])."""
    cams = _LAYOUTS[layout]()
    got, ref = _entry_point(backend, cams, shared), _entry_point("torch", cams, shared)
    equal = len({(c.width, c.height) for c in cams}) == 1
    assert isinstance(got[0], torch.Tensor) == equal and isinstance(got[1], torch.Tensor) == equal
    for b, cam in enumerate(cams):
        assert got[0][b].shape == (cam.height, cam.width, 3) and got[1][b].shape == (cam.height, cam.width)
        assert (got[0][b] - ref[0][b]).abs().max() < 1e-5 and (got[1][b] - ref[1][b]).abs().max() < 1e-5
    assert torch.equal(got[2].radii, ref[2].radii) and torch.equal(got[2].depths, ref[2].depths)
    for name, g, r in zip(["means", "covars", "colors", "opacities", "means2d"], got[3] + [got[2].means2d.grad],
                          ref[3] + [ref[2].means2d.grad]):
        assert g.shape == r.shape and float((g - r).abs().max() / r.abs().max()) < 1e-4, name


def test_the_meta_record_of_a_batch():
    """SplatMeta of three images: per image the projection of its own camera (radii, 2D means, depths), and
    means2d's retained gradient is the densification statistic: non-zero exactly where a Gaussian drew pixels."""
    cams = _LAYOUTS["unequal"]()
    _, _, meta, _ = _entry_point("warp", cams, shared=False)
    B, G = len(cams), 60
    assert isinstance(meta, SplatMeta) and meta.radii.dtype == torch.int32
    assert (meta.radii.shape, meta.means2d.shape, meta.depths.shape) == ((B, G), (B, G, 2), (B, G))
    for b, cam in enumerate(cams):
        sc = _scene(b)
        one = project_gaussians(sc[0][None], sc[1][None], [cam])
        assert torch.equal(meta.radii[b], one.radii[0]) and int((one.radii[0] == 0).sum()) >= 4
        assert torch.allclose(meta.means2d[b], one.means2d[0], atol=1e-5)
        assert torch.allclose(meta.depths[b], one.depths[0], atol=1e-6)
    norm = meta.means2d.grad.norm(dim=-1)  # [B, G]
    assert not norm[meta.radii == 0].any() and (norm[meta.radii > 0] > 0).float().mean() > 0.9


@pytest.mark.parametrize("backend", WARP)
def test_the_backward_computes_only_the_gradients_required(backend, monkeypatch):
    """Frozen colours: the kernels are told to skip the colour gradient (and frozen geometry the gradients through
    alpha), and the gradients still required are those of a backward that computes everything, bit for bit."""
    import avatarctl.splat.rasterizer as rasterizer

    cams = _LAYOUTS["unequal"]()
    flags = []
    real = rasterizer._launch
    monkeypatch.setattr(rasterizer, "_launch", lambda kernel, bins, per_tile, jobs, args_of_job, *rest: (
        flags.append(tuple(a for a in args_of_job(0) if type(a) is int)[-2:]) if "backward" in kernel.key else None,
        real(kernel, bins, per_tile, jobs, args_of_job, *rest))[1])
    full = _entry_point(backend, cams, shared=False)
    no_colors = _entry_point(backend, cams, shared=False, frozen=(2,))
    colors_only = _entry_point(backend, cams, shared=False, frozen=(0, 1, 3))
    assert flags == [(1, 1), (0, 1), (1, 0)]  # (colour gradient, gradients through alpha)
    assert no_colors[3][2] is None and all(g is None for i, g in enumerate(colors_only[3]) if i != 2)
    for i in (0, 1, 3):
        assert torch.equal(no_colors[3][i], full[3][i])
    assert torch.equal(colors_only[3][2], full[3][2])


def _hard_scene(seed: int):
    """`_scene` plus the rows that take the culling branches: behind the near plane, a covariance of NaNs, a zero
    covariance (only the low-pass left), opacities under ALPHA_MIN, Gaussians far outside the window."""
    means, covars, colors, opacities = _scene(seed, G=80)
    means[4, 2] = 0.005
    covars[5] = float("nan")
    covars[6] = 0.0
    opacities[7:10] = torch.tensor([0.0, 1e-3, 1.0 / 255.0])
    means[10:14, :2] = torch.tensor([[40.0, 0.0], [-40.0, 3.0], [0.0, 60.0], [3.0, -35.0]])
    return means, covars, colors, opacities


def _fused_against_pair(device: str) -> None:
    """Three cameras of three sizes at once: the fused kernel's rows and boxes per image, and on their canvas."""
    cams = [_camera(), _camera(20, 45, f=25.0).crop(-3, 4, 20, 45), _camera(64, 48)]
    means, covars, _, opacities = (torch.stack(t) for t in zip(*(_hard_scene(seed) for seed in range(3))))
    pair = project_gaussians(means, covars, cams)
    fused = project_and_reach(means.to(device), covars.to(device), opacities.to(device), [c.to(device) for c in cams])
    for b, cam in enumerate(cams):
        boxes = reach(_project(means[b], covars[b], cam), opacities[b], cam.width, cam.height)
        for name in ("means2d", "conics", "depths"):  # the torch conic of the NaN covariance is NaN (culled): 0 here
            want = torch.nan_to_num(getattr(pair, name)[b], nan=0.0)
            assert torch.allclose(getattr(fused, name)[b].cpu(), want, atol=1e-5, rtol=1e-5), name
        assert torch.equal(fused.radii[b].cpu(), pair.radii[b]) and torch.equal(fused.reach[b].cpu(), boxes)
        assert int((pair.radii[b] == 0).sum()) >= 4 and int((boxes[:, 0] > boxes[:, 2]).sum()) >= 6  # culled rows
    canvas = Canvas.of(pair, [(c.width, c.height) for c in cams])  # the boxes move down with their images
    want = reach(canvas.proj, opacities.reshape(-1), canvas.width, canvas.height)
    got = Canvas.of(fused, canvas.sizes).proj.reach.cpu()
    empty = (want[:, 0] > want[:, 2]) | (want[:, 1] > want[:, 3])
    assert torch.equal(empty, (got[:, 0] > got[:, 2]) | (got[:, 1] > got[:, 3])) and torch.equal(got[~empty],
                                                                                                 want[~empty])


def test_fused_projection_matches_the_torch_pair():
    """`project_and_reach` (one Warp kernel per camera, rendering without gradients) = `project_gaussians` + `reach`,
    the culling branches included."""
    _fused_against_pair("cpu")


def test_rendering_without_gradients_uses_the_fused_projection(monkeypatch):
    """`rasterization` under no_grad projects with the fused kernel and gives the image of the torch projection, one
    image or a batch; with gradients to keep it projects in torch (the fused kernel has no backward)."""
    import avatarctl.splat.rendering as rendering

    means, covars, colors, opacities = _hard_scene(3)
    bg = torch.tensor([0.2, 0.5, 0.9])
    cams = [_camera(), _camera(20, 45, f=25.0).crop(-3, 4, 20, 45)]
    ref = rasterization(means, covars, colors, opacities, cams, bg, backend="torch")
    calls = []
    monkeypatch.setattr(rendering, "project_and_reach", lambda *a, **k: calls.append(1) or project_and_reach(*a, **k))
    for n in (1, 2):
        with torch.no_grad():
            out = rasterization(means, covars, colors, opacities, cams[:n], bg)
        assert len(calls) == n and torch.equal(out[2].radii, ref[2].radii[:n])
        for b in range(n):
            assert (out[0][b] - ref[0][b]).abs().max() < 1e-5 and (out[1][b] - ref[1][b]).abs().max() < 1e-5
    # a smaller low-pass reaches the fused kernel too: sharper splats, the torch path's image, not the default's
    sharp = rasterization(means, covars, colors, opacities, cams[:1], bg, backend="torch", low_pass=0.05)
    with torch.no_grad():
        out = rasterization(means, covars, colors, opacities, cams[:1], bg, low_pass=0.05)
    assert (out[0] - sharp[0]).abs().max() < 1e-5 and (sharp[0][0] - ref[0][0]).abs().max() > 1e-3
    calls.clear()
    rasterization(means.requires_grad_(), covars, colors, opacities, cams, bg)
    assert not calls


@pytest.mark.gpu
def test_cuda_fused_projection_matches_the_torch_pair():
    _fused_against_pair("cuda")


@pytest.mark.gpu
def test_cuda_batched_rendering_matches_one_image_at_a_time():
    img, grad = _batched_against_single("warp", "cuda")
    assert img < 1e-5 and grad < 1e-4


@pytest.mark.gpu
@pytest.mark.parametrize("backend", WARP)
def test_cuda_matches_the_twin(backend):
    means, covars, colors, opacities = _scene(7)
    bg = torch.tensor([0.2, 0.5, 0.9])
    proj = _project(means, covars, _camera())
    ref_rgb, ref_alpha = rasterize_torch(proj, colors, opacities, W, H, bg)
    ref = _grads("twin", proj, colors, opacities, bg)
    cuda = Projected(*(t.cuda() for t in (proj.means2d, proj.conics, proj.depths, proj.radii)))  # one canvas
    args = colors.cuda(), opacities.cuda(), W, H, bg.cuda()
    rgb, alpha = _raster(cuda, *args, backend=backend)
    assert (rgb.cpu() - ref_rgb).abs().max() < 1e-5 and (alpha.cpu() - ref_alpha).abs().max() < 1e-5
    got = _grads(backend, cuda, colors.cuda(), opacities.cuda(), bg.cuda())
    for g, r in zip(got, ref):
        assert float((g.cpu() - r).abs().max() / r.abs().max()) < 1e-4
