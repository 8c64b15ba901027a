"""Volume compositing against analytic cases; samplers; camera rays."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from avatarctl.geometry.cameras import Camera, look_at
from avatarctl.geometry.rays import RayBatch, camera_rays, image_pixels
from avatarctl.render.volume import composite, march, sample_deltas, uniform_samples


def test_constant_density_slab_matches_beer_lambert():
    near, far = torch.tensor([1.0, 2.0]), torch.tensor([1.5, 4.0])
    t = uniform_samples(near, far, 64)
    sigma = torch.full((2, 64), 3.0)
    rgb = torch.tensor([1.0, 0.0, 0.0]).expand(2, 64, 3)
    bg = torch.tensor([0.0, 0.0, 1.0])
    c, alpha, depth, w = composite(rgb, sigma, t, bg)
    L = far - near
    want = 1 - torch.exp(-3.0 * L)
    assert torch.allclose(alpha, want, atol=1e-6)
    assert torch.allclose(c[:, 0], want, atol=1e-6) and torch.allclose(c[:, 2], 1 - want, atol=1e-6)
    assert torch.allclose(w.sum(-1), alpha)
    # expected depth of an exponential distribution truncated to the slab (quadrature error ~ spacing^2)
    s = 3.0
    want_depth = near + 1 / s - L * torch.exp(-s * L) / (1 - torch.exp(-s * L))
    assert torch.allclose(depth, want_depth, atol=2e-3)


def test_opaque_wall_and_empty_space():
    t = uniform_samples(torch.tensor([0.0, 0.0]), torch.tensor([1.0, 1.0]), 10)
    sigma = torch.zeros(2, 10)
    sigma[0, 5:] = 1e4  # a wall from t = 0.5
    rgb = torch.full((2, 10, 3), 0.25)
    c, alpha, depth, _ = composite(rgb, sigma, t, torch.ones(3))
    assert alpha[0] == pytest.approx(1.0) and depth[0] == pytest.approx(0.55, abs=1e-4)
    assert torch.allclose(c[0], torch.full((3,), 0.25), atol=1e-5)
    assert alpha[1] == 0 and depth[1] == 0 and torch.allclose(c[1], torch.ones(3))


def test_uniform_samples_bins_and_jitter():
    near, far = torch.zeros(3), torch.full((3,), 2.0)
    t = uniform_samples(near, far, 4)
    assert torch.allclose(t[0], torch.tensor([0.25, 0.75, 1.25, 1.75]))
    assert torch.allclose(sample_deltas(t).sum(-1), far - near)
    g1, g2 = torch.Generator().manual_seed(5), torch.Generator().manual_seed(5)
    tj = uniform_samples(near, far, 4, jitter=True, generator=g1)
    assert torch.equal(tj, uniform_samples(near, far, 4, jitter=True, generator=g2))
    bins = torch.floor(tj / 0.5)
    assert torch.equal(bins, torch.arange(4.0).expand(3, 4))  # one sample per bin
    assert bool((tj[:, 1:] > tj[:, :-1]).all())


def test_march_analytic_sphere():
    """A unit-density-inside sphere of radius 1 at the origin: alpha = 1 - exp(-chord length)."""
    def field(p, d):
        inside = (p.norm(dim=-1) < 1.0).float()
        return torch.ones(*p.shape[:-1], 3) * 0.5, inside * 1.0

    offsets = torch.tensor([0.0, 0.5, 0.9])
    o = torch.stack([offsets, torch.zeros(3), torch.full((3,), -3.0)], dim=-1)
    d = torch.tensor([0.0, 0.0, 1.0]).expand(3, 3)
    out = march(field, o, d, torch.full((3,), 1.5), torch.full((3,), 4.5), 4096, torch.zeros(3))
    chord = 2 * torch.sqrt(1 - offsets ** 2)
    assert torch.allclose(out.alpha, 1 - torch.exp(-chord), atol=2e-3)


def test_camera_rays_hit_the_projected_points():
    R, T = look_at(np.array([0.0, -3.0, 1.0]), np.array([0.0, 0.0, 0.0]))
    cam = Camera("c", K=np.array([[200.0, 0, 31.5], [0, 210.0, 23.5], [0, 0, 1]]), R=R, T=T, width=64, height=48)
    pts = np.array([[0.1, 0.2, 0.3], [-0.4, 0.1, -0.2]])
    uv = torch.tensor(cam.project(pts), dtype=torch.float32)
    o, d = camera_rays(cam, uv)
    assert torch.allclose(d.norm(dim=-1), torch.ones(2), atol=1e-6)
    assert torch.allclose(o[0], torch.tensor(cam.center, dtype=torch.float32), atol=1e-6)
    # the world point lies on its ray
    v = torch.tensor(pts, dtype=torch.float32) - o
    along = (v * d).sum(-1, keepdim=True)
    assert torch.allclose(o + along * d, torch.tensor(pts, dtype=torch.float32), atol=1e-5)
    with pytest.raises(ValueError, match="pinhole"):
        camera_rays(Camera("d", K=cam.K, R=R, T=T, width=64, height=48, dist=np.array([0.1, 0, 0, 0, 0])), uv)


def test_image_pixels_row_major():
    px = image_pixels(3, 2)
    assert px.shape == (6, 2)
    assert px.tolist() == [[0, 0], [1, 0], [2, 0], [0, 1], [1, 1], [2, 1]]


def test_raybatch_shape_check():
    with pytest.raises(AssertionError, match="frame_slot"):
        RayBatch(torch.zeros(4, 3), torch.zeros(4, 3), torch.zeros(3, dtype=torch.long))
    rb = RayBatch(torch.zeros(4, 3), torch.ones(4, 3), torch.arange(4))
    assert len(rb.select(slice(1, 3))) == 2 and len(RayBatch.cat([rb, rb])) == 8
    assert math.isclose(float(rb.to("cpu").dirs.sum()), 12.0)
