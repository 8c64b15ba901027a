"""fit/flow.py: the training views' optical flow (a shifted texture moves by its shift), sampling it, projecting."""

from __future__ import annotations

import numpy as np
import torch


class _ShiftedCapture:
    """Frames 0..3 of one view: a smooth random texture moved 2 px right and 1 px down per frame."""

    def __init__(self):
        rng = np.random.default_rng(0)
        import cv2

        base = cv2.GaussianBlur(rng.uniform(0, 255, (96, 96)).astype(np.float32), (0, 0), 2.0)
        self.frames = {t: np.roll(np.roll(base, 2 * t, axis=1), t, axis=0) for t in range(4)}

    def image(self, view: str, frame: int) -> np.ndarray:
        g = np.clip(self.frames[frame], 0, 255).astype(np.uint8)
        return np.stack([g, g, g], -1)


def test_training_flow_follows_a_shifted_texture_between_consecutive_training_frames():
    from avatarctl.fit.flow import sample_flow, training_flows

    flows = training_flows(_ShiftedCapture(), [0, 1, 3], ["cam"])
    assert set(flows.flows) == {("cam", 0)}  # 1 -> 2 and 3 -> 4 are not both training frames
    assert flows.next_frame("cam", 0) == 1 and flows.next_frame("cam", 1) is None
    f = flows.flows[("cam", 0)]
    centre = f[24:72, 24:72].reshape(-1, 2)
    assert torch.allclose(centre.median(0).values, torch.tensor([2.0, 1.0]), atol=0.25)
    at = sample_flow(f, torch.tensor([[40.0, 50.0], [40.5, 50.5]]))
    assert torch.allclose(at[0], f[50, 40], atol=1e-5) and at.shape == (2, 2)


def test_projection_matches_the_calibrated_camera():
    from avatarctl.fit.flow import project_points
    from avatarctl.geometry.cameras import Camera, look_at
    from avatarctl.geometry.triangulate import project, projection_matrices
    from avatarctl.splat import SplatCamera

    R, T = look_at(np.array([0.5, -3.0, 1.0]), np.zeros(3))
    cam = Camera("c", np.array([[200.0, 0, 64], [0, 210.0, 60], [0, 0, 1]]), R, T, 128, 120)
    pts = np.random.default_rng(1).uniform(-0.5, 0.5, (20, 3))
    uv, z = project_points(torch.tensor(pts, dtype=torch.float32), SplatCamera.from_camera(cam))
    ref, depth = project(projection_matrices([cam]), pts)
    assert np.allclose(uv.numpy(), ref[:, 0], atol=1e-3) and np.allclose(z.numpy(), depth[:, 0], atol=1e-4)
