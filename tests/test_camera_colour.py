"""The per-camera colour transform (issue 51): the formula, its least-squares estimate (eval), the learned module
(model/colour.py) recovering a known gain and offset, and fits with it on for both field kinds (toy body, seconds)."""

from __future__ import annotations

import numpy as np
import pytest
import torch


def _scene(seed: int = 0, shape=(40, 50)):
    rng = np.random.default_rng(seed)
    alpha = np.clip(rng.uniform(-0.3, 1.3, shape), 0, 1).astype(np.float32)  # [H, W] opaque, clear and in between
    colour = rng.uniform(0.1, 0.8, shape + (3,)).astype(np.float32)  # the subject's colour
    bg = np.array([0.2, 0.1, 0.3], np.float32)
    rgb = alpha[..., None] * colour + (1 - alpha[..., None]) * bg  # composited over the background
    return rgb, alpha, bg


def test_apply_colour_changes_the_foreground_only_and_is_the_identity_at_one_and_zero():
    from avatarctl.evaluate.colour import apply_colour

    rgb, alpha, bg = _scene()
    assert np.allclose(apply_colour(rgb, alpha, bg, np.ones(3), np.zeros(3)), rgb)
    out = apply_colour(rgb, alpha, bg, np.array([0.5, 1.0, 2.0]), np.array([0.1, 0.0, -0.1]))
    clear = alpha == 0
    assert clear.any() and np.allclose(out[clear], bg)  # the background colour never changes
    opaque = alpha == 1
    assert np.allclose(out[opaque], rgb[opaque] * [0.5, 1.0, 2.0] + [0.1, 0.0, -0.1])
    t = apply_colour(torch.from_numpy(rgb), torch.from_numpy(alpha), torch.from_numpy(bg), torch.tensor([0.5, 1, 2]),
                     torch.tensor([0.1, 0.0, -0.1]))  # torch and numpy: one formula
    assert np.allclose(t.numpy(), out, atol=1e-6)


def test_estimate_colour_recovers_a_known_transform_and_stays_at_identity_without_foreground():
    from avatarctl.evaluate.colour import apply_colour, estimate_colour, halves

    rgb, alpha, bg = _scene(1)
    gain = np.array([0.8, 0.85, 1.2])
    gt = apply_colour(rgb, alpha, bg, gain, np.zeros(3))
    mask = np.ones(alpha.shape, bool)
    g, o = estimate_colour(rgb, alpha, gt, bg, mask, ridge=1e-9)
    assert np.allclose(g, gain, atol=1e-4) and np.allclose(o, 0.0)
    # a blurred, shifted render (what a held-out view is) still gives the camera's gain, not the mean colour
    import cv2

    soft = cv2.GaussianBlur(np.roll(rgb, 2, axis=1).astype(np.float32), (7, 7), 2.0)
    g, _ = estimate_colour(soft, cv2.GaussianBlur(np.roll(alpha, 2, axis=1).astype(np.float32), (7, 7), 2.0), gt,
                           bg, mask, ridge=1e-9)
    assert np.allclose(g, gain, rtol=0.08), g
    empty = np.broadcast_to(bg, rgb.shape)  # nothing rendered: nothing to estimate from
    g, o = estimate_colour(empty, np.zeros_like(alpha), gt, bg, mask)
    assert np.allclose(g, 1.0) and np.allclose(o, 0.0)
    left, right = halves(mask, (10, 0, 30, 40))
    assert left[:, :20].all() and not left[:, 20:].any() and (left ^ right).all()


def test_camera_colour_recovers_a_known_gain_and_offset_on_a_toy_fit():
    """Two cameras see one subject (a learned colour per pixel); camera 1 records it darker and shifted. Adam on the
    L2 loss of both renders finds camera 1's transform relative to camera 0 (the centred gauge leaves their mean at
    identity: the subject learns the cameras' mean colour)."""
    from avatarctl.evaluate.colour import apply_colour
    from avatarctl.model.colour import CameraColour

    rgb, alpha, bg = _scene(2, (16, 16))
    gain, offset = torch.tensor([0.7, 0.75, 0.65]), torch.tensor([0.03, -0.02, 0.05])
    a, b = torch.from_numpy(alpha), torch.from_numpy(bg)
    fg = (torch.from_numpy(rgb) - (1 - a[..., None]) * b)  # premultiplied true colour
    targets = torch.stack([fg + (1 - a[..., None]) * b,
                           apply_colour(fg + (1 - a[..., None]) * b, a, b, gain, offset)])  # [cams, H, W, 3]
    colour = CameraColour(["cam00", "cam01"])
    subject = torch.nn.Parameter(torch.full((16, 16, 3), 0.4))
    opt = torch.optim.Adam([{"params": [subject], "lr": 0.02}, {"params": colour.parameters(), "lr": 0.02}])
    cams = torch.arange(2)[:, None, None].expand(2, 16, 16)
    for _ in range(400):
        render = (a[..., None] * subject + (1 - a[..., None]) * b).expand(2, -1, -1, -1)
        loss = ((colour(render, a.expand(2, -1, -1), b, cams) - targets) ** 2).mean() + 1e-6 * colour.penalty()
        opt.zero_grad()
        loss.backward()
        opt.step()
    g, o = colour.transforms()
    assert torch.allclose(g.prod(0), torch.ones(3), atol=1e-5) and torch.allclose(o.sum(0), torch.zeros(3), atol=1e-6)
    assert torch.allclose(g[1] / g[0], gain, atol=0.03)
    assert torch.allclose(o[1] - g[1] / g[0] * o[0], offset, atol=0.03)
    assert colour.of("cam01") is not None and colour.of("cam03") is None


def test_colour_config_and_one_camera_is_the_identity():
    from avatarctl.fit.config import resolve_fit_config
    from avatarctl.model.colour import CameraColour

    cfg = resolve_fit_config("micro", overrides=["model.colour.enabled=true"])
    assert cfg.model.colour.enabled and cfg.model.with_(colour={"lr": 0.01}).colour.lr == 0.01
    assert not resolve_fit_config("micro").model.colour.enabled  # off until measured
    with pytest.raises(ValueError, match="lambda_identity"):
        cfg.model.with_(colour={"lambda_identity": -1.0})
    one = CameraColour(["cam00"])
    with torch.no_grad():
        one.log_gain.fill_(0.5)
    g, o = one.transforms()
    assert torch.allclose(g, torch.ones(1, 3)) and float(one.penalty().detach()) == 0.0


def _darken(cap, view: str, gain: float) -> None:
    import cv2

    for p in sorted((cap / "images" / view).glob("*.jpg")):
        img = cv2.imread(str(p)).astype(np.float32) * gain
        cv2.imwrite(str(p), np.clip(img, 0, 255).round().astype(np.uint8), [cv2.IMWRITE_JPEG_QUALITY, 100])


@pytest.mark.parametrize("field", ["mlp", "gaussians"])
def test_a_fit_with_camera_colour_learns_the_darker_camera_and_reloads(tmp_path, field):
    from fixtures.toy_capture import make_toy_capture

    from avatarctl.fit.checkpoint import load_avatar
    from avatarctl.project import Project
    from avatarctl.stages import fit, ingest
    from avatarctl.stages.fit import FitRequest
    from avatarctl.stages.ingest import IngestConfig

    cap, proj = make_toy_capture(tmp_path / "cap"), tmp_path / "proj"
    _darken(cap, "cam02", 0.6)  # a training camera (cam00 and cam02 train)
    ingest.run(proj, IngestConfig(capture=cap, project=proj, contact_sheet=False))
    sets = ["val_every=0", "model.colour.enabled=true"]
    if field == "gaussians":
        sets += ["model.field=gaussians", "model.gaussians.per_node=16"]
    res = fit.run(proj, FitRequest(preset="micro", iters=40, overrides=tuple(sets), device="cpu",
                                   model_settings={"colour": {"lr": 0.02, "lambda_identity": 0.0}}),
                  handle_sigint=False)
    assert "colour" in res.losses
    av = load_avatar(Project.open(proj), device="cpu")
    colour = av.model.camera_colour
    assert colour is not None and colour.names == ("cam00", "cam02")
    (g0, o0), (g2, o2) = (map(np.array, colour.of(v)) for v in ("cam00", "cam02"))
    # what each camera makes of the subject's mean colour: cam02 sees it 0.6 times as bright as cam00. Red and blue
    # only: the toy body's green is its canonical y (cam00 sees the front, low; cam02 the back, high), which 40 steps
    # of a fit cannot yet tell from a camera's colour
    mean = np.array([0.54, 0.25, 0.54])  # cam00's foreground, frame 0
    ratio = (g2 * mean + o2) / (g0 * mean + o0)
    assert (np.abs(ratio[[0, 2]] - 0.6) < 0.1).all(), ratio


# ---- the cameras' gains from the body's colours across cameras (ingest) ------------------------------------------
def _sphere_views(gains: np.ndarray, size: int = 96):
    """A sphere (radius 0.3 m) whose colour is a smooth function of the surface point, ray-cast into 4 cameras 90
    degrees apart, each image through its camera's gains [4, 3] -> (cameras, images, masks, vertices, faces)."""
    import trimesh

    from avatarctl.geometry.cameras import Camera, look_at
    from avatarctl.geometry.raycast import RayCaster
    from avatarctl.geometry.rays import camera_rays, image_pixels

    mesh = trimesh.creation.icosphere(subdivisions=5, radius=0.3)
    V, F = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    caster = RayCaster(V, F)
    cams, images, masks = [], [], []
    for i in range(4):
        a = 2 * np.pi * i / 4
        R, T = look_at(np.array([2.0 * np.cos(a), 2.0 * np.sin(a), 0.3]), np.zeros(3))
        cam = Camera(f"c{i}", np.array([[150.0, 0, size / 2], [0, 150.0, size / 2], [0, 0, 1]]), R, T, size, size)
        d = camera_rays(cam, image_pixels(size, size))[1].double().numpy()  # [H*W, 3] unit, row-major
        face, t = caster.cast(cam.center, d)
        hit = face >= 0
        p = cam.center + t[hit, None] * d[hit]
        img = np.zeros((len(d), 3))
        img[hit] = 0.45 + 0.25 * np.stack([np.sin(6 * p[:, 0]), np.cos(5 * p[:, 1] + 1), np.sin(4 * p[:, 2] + 2)], -1)
        img = np.clip(img * gains[i], 0, 1)
        cams.append(cam)
        images.append((img.reshape(size, size, 3) * 255).round().astype(np.uint8))
        masks.append(hit.reshape(size, size))
    return cams, images, masks, V, F


def test_shared_colours_recover_the_cameras_gains_relative_to_the_training_cameras():
    from avatarctl.evaluate.colour import CameraGains, SharedColours

    gains = np.array([[1.0, 0.95, 1.05], [1.3, 1.25, 1.2], [0.8, 0.85, 0.9], [1.1, 1.0, 0.9]])
    cams, images, masks, V, F = _sphere_views(gains)
    shared = SharedColours([c.name for c in cams])
    for _ in range(4):  # four frames of a still scene: each reads its own `POINTS` of the vertices
        shared.add(cams, images, masks, V, F)
    est = shared.solve(["c0", "c1", "c3"])  # c2 held out
    want = gains / np.exp(np.log(gains[[0, 1, 3]]).mean(0))  # relative to the training cameras' mean
    assert est.estimated.all() and (est.points > 1000).all(), est.points
    np.testing.assert_allclose(est.gain, want, rtol=0.02)
    assert np.allclose(np.log(est.gain[[0, 1, 3]]).mean(0), 0, atol=1e-6)  # the gauge
    np.testing.assert_allclose(est.of("c2"), want[2], rtol=0.02)
    back = CameraGains.from_json(est.to_json())  # ingest/camera_colour.json round trip (5 decimals)
    np.testing.assert_allclose(back.gain, est.gain, atol=1e-5)
    assert back.views == est.views and (back.estimated == est.estimated).all()
    # a camera that shares no point with a training camera keeps gain 1, and says so
    lone = SharedColours([c.name for c in cams])
    for _ in range(4):
        lone.add(cams, images, [m if i != 2 else np.zeros_like(m) for i, m in enumerate(masks)], V, F)
    est = lone.solve(["c0", "c1", "c3"])
    assert not est.estimated[2] and est.of("c2") is None and np.allclose(est.gain[2], 1.0)
    np.testing.assert_allclose(est.gain[[0, 1, 3]], want[[0, 1, 3]], rtol=0.02)


def test_ingest_estimates_a_darker_held_out_camera_and_eval_renders_through_it(tmp_path):
    from fixtures.toy_capture import make_toy_capture

    from avatarctl.io.project_io import load_camera_colour
    from avatarctl.project import Project
    from avatarctl.stages import evaluate, fit, ingest
    from avatarctl.stages.evaluate import EvalConfig
    from avatarctl.stages.fit import FitRequest
    from avatarctl.stages.ingest import IngestConfig

    cap, proj = make_toy_capture(tmp_path / "cap"), tmp_path / "proj"
    _darken(cap, "cam01", 0.6)  # a held-out camera (cam00 and cam02 train)
    res = ingest.run(proj, IngestConfig(capture=cap, project=proj, contact_sheet=False))
    gains = load_camera_colour(Project.open(proj))
    assert res.camera_colour is not None and gains is not None and gains.views == tuple(res.cameras)
    g = gains.of("cam01")
    assert g is not None and (np.abs(g - 0.6) < 0.08).all(), g
    assert np.allclose(np.log(gains.gain[[gains.views.index("cam00"), gains.views.index("cam02")]]).mean(0), 0,
                       atol=1e-4)  # the gauge (5 decimals in the file)
    fit.run(proj, FitRequest(preset="micro", iters=5, overrides=("val_every=0",), device="cpu"), handle_sigint=False)
    on = evaluate.run(proj, EvalConfig(views=("cam01",), sheet_rows=0, name="on"))
    off = evaluate.run(proj, EvalConfig(views=("cam01",), sheet_rows=0, name="off", camera_colour="off"))
    assert off.metrics.camera_colour is None
    assert on.metrics.camera_colour["gain"] == {"cam01": [round(float(x), 4) for x in g]}
    assert on.metrics.psnr != off.metrics.psnr  # the held-out render went through the gains
