"""Optical flow of the training views between consecutive training frames (`model.gaussians.lambda_flow`, a
deviation, issue 28): where the cloth moves from frame t to t + 1 in each view, a signal the photometric loss of a
high-frequency print does not give (docs/fit.md, "Why the skirt stays a blur").

Flow: OpenCV's Farnebäck (pyramid of 4 levels at scale 0.5, window 15, 5 iterations) on the grey ingested,
undistorted images, frame t -> t + 1, pixels [H, W, 2] (x, y). Measured against the true motion of synth small's skirt
(`benchmarks.garment_tracking --flow`): 0.55 px median error for a 2.26 px median motion.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass(frozen=True)
class FrameFlows:
    """Flow of each training view from each training frame whose next frame is also a training frame."""

    flows: dict[tuple[str, int], torch.Tensor]  # (view, t) -> [H, W, 2] float32 pixels, t -> t + 1

    def next_frame(self, view: str, frame: int) -> int | None:
        """t + 1 when the flow (view, t) exists, else None."""
        return int(frame) + 1 if (view, int(frame)) in self.flows else None


def training_flows(capture, frames: list[int], views: list[str]) -> FrameFlows:
    """`FrameFlows` of `capture` (a `ProjectCapture`) for its training `frames` and `views`."""
    import cv2

    have = set(int(f) for f in frames)
    out = {}
    for view in views:
        prev = None
        for t in sorted(have):
            if t + 1 not in have:
                prev = None
                continue
            a = prev if prev is not None else cv2.cvtColor(capture.image(view, t), cv2.COLOR_RGB2GRAY)
            b = cv2.cvtColor(capture.image(view, t + 1), cv2.COLOR_RGB2GRAY)
            out[(view, t)] = torch.from_numpy(cv2.calcOpticalFlowFarneback(a, b, None, 0.5, 4, 15, 5, 5, 1.1, 0))
            prev = b
    return FrameFlows(flows=out)


def sample_flow(flow: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """flow [H, W, 2], uv [P, 2] pixel coordinates (x, y) -> [P, 2] bilinear flow there (border values outside)."""
    H, W = flow.shape[:2]
    g = torch.stack([2 * uv[:, 0] / max(W - 1, 1) - 1, 2 * uv[:, 1] / max(H - 1, 1) - 1], -1)
    f = torch.nn.functional.grid_sample(flow.permute(2, 0, 1)[None].to(uv), g[None, None], mode="bilinear",
                                        padding_mode="border", align_corners=True)  # [1, 2, 1, P]
    return f[0, :, 0].T


def project_points(points: torch.Tensor, cam) -> tuple[torch.Tensor, torch.Tensor]:
    """points [P, 3] world, cam a `SplatCamera` -> (uv [P, 2] pixels of its window, depth [P] metres)."""
    x = points @ cam.R.T.to(points) + cam.T.to(points)
    z = x[:, 2].clamp(min=1e-6)
    uvw = x @ cam.K.T.to(points)
    return uvw[:, :2] / z[:, None], x[:, 2]

