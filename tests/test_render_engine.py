"""`render_view`: whole-view rendering of a model (toy sphere body, no body model file needed)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from avatarctl.model.avatar import FrameConditioning, SlrfAvatar
from avatarctl.fit.config import preset
from avatarctl.body.toy import sphere_template, toy_joint_transforms
from avatarctl.geometry.cameras import Camera, look_at
from avatarctl.render.engine import rays_hitting_spheres, render_view
from avatarctl.geometry.rays import RayBatch, camera_rays, image_pixels

SIZE = 24
BG = (0.1, 0.5, 0.9)


@pytest.fixture(scope="module")
def scene():
    torch.manual_seed(0)
    cfg = preset("cpu-mlp").model.with_(num_nodes=12, samples_per_ray=8, pose_refine={"enabled": False})
    model = SlrfAvatar(cfg, sphere_template(120, radius=0.2), num_frames=2, seed=0).eval()
    M, aa = toy_joint_transforms(torch.tensor([0.0, 0.6]))
    cond = FrameConditioning(M, aa, time=torch.tensor([0.0, 0.5]), frame_ids=torch.tensor([0, 1]))
    with torch.no_grad():
        state = model.node_state(cond, mode="mean")
    R, T = look_at(np.array([0.0, -1.5, 0.0]), np.zeros(3))
    K = np.array([[SIZE * 1.2, 0, (SIZE - 1) / 2], [0, SIZE * 1.2, (SIZE - 1) / 2], [0, 0, 1]])
    cam = Camera(name="c", K=K, R=R, T=T, width=SIZE, height=SIZE)
    return model, state, cam


def test_rays_hitting_spheres_analytic():
    origin = torch.zeros(3)
    dirs = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.6, 0.8], [0.0, 0.0, -1.0]])
    # centre 0 is 0.5 from ray 0 (and 0.8 from ray 1); centre 1 lies on ray 1; ray 2 points away from both
    centers = torch.tensor([[0.0, 0.5, 2.0], [0.0, 1.5, 2.0]])
    assert rays_hitting_spheres(origin, dirs, centers, 0.4).tolist() == [False, True, False]
    assert rays_hitting_spheres(origin, dirs, centers, 0.6).tolist() == [True, True, False]
    inside = rays_hitting_spheres(origin, dirs, torch.zeros(1, 3), 0.1)  # camera inside a sphere: all hit
    assert inside.all()


def test_render_view_matches_rendering_every_pixel(scene):
    model, state, cam = scene
    view = render_view(model, state, 1, cam, BG)
    assert view.rgb.shape == (SIZE, SIZE, 3) and view.alpha.shape == (SIZE, SIZE)
    assert view.rgb.dtype == np.float32 and np.isfinite(view.rgb).all() and np.isfinite(view.alpha).all()
    assert 0 < view.rays < SIZE * SIZE and view.seconds > 0
    # the skipped rays are exactly those that render as background: compare with rendering all pixels
    o, d = camera_rays(cam, image_pixels(SIZE, SIZE))
    with torch.no_grad():
        full = model.render(RayBatch(o, d, torch.ones(SIZE * SIZE, dtype=torch.long)), state,
                            torch.tensor(BG))
    np.testing.assert_allclose(view.rgb, full.rgb.numpy().reshape(SIZE, SIZE, 3).clip(0, 1), atol=1e-5)
    np.testing.assert_allclose(view.alpha, full.alpha.numpy().reshape(SIZE, SIZE), atol=1e-5)
    assert np.allclose(view.rgb[0, 0], BG) and view.alpha[0, 0] == 0  # a corner sees no node


def test_render_view_respects_pixel_mask_and_chunking(scene):
    model, state, cam = scene
    whole = render_view(model, state, 1, cam, BG)
    mask = np.zeros((SIZE, SIZE), bool)
    mask[SIZE // 2:, :] = True
    calls = []
    part = render_view(model, state, 1, cam, BG, max_rays_per_chunk=7, pixel_mask=mask,
                       progress=lambda p: calls.append((p.done, p.total, p.part)))
    np.testing.assert_allclose(part.rgb[mask], whole.rgb[mask], atol=1e-6)
    np.testing.assert_allclose(part.rgb[~mask], np.broadcast_to(np.float32(BG), part.rgb[~mask].shape))
    assert (part.alpha[~mask] == 0).all() and part.rays < whole.rays
    assert calls[-1] == (part.rays, part.rays, "rays") and len(calls) == -(-part.rays // 7)
    with pytest.raises(ValueError, match="pixel_mask"):
        render_view(model, state, 1, cam, BG, pixel_mask=np.ones((3, 3), bool))


def test_render_view_frame_slot_selects_the_pose(scene):
    model, state, cam = scene
    a, b = render_view(model, state, 0, cam, BG), render_view(model, state, 1, cam, BG)
    assert not np.allclose(a.alpha, b.alpha)  # the upper hemisphere is bent in slot 1
    with pytest.raises(IndexError):
        render_view(model, state, 2, cam, BG)
