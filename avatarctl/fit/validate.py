"""Held-out-view validation during training: PSNR (bbox protocol) on a small fixed set of
(held-out view, training frame) pairs, through the one metrics module (`avatarctl.evaluate.metrics`).

Pairs (`choose_val_pairs`): the i-th pair takes held-out view i mod V and the training frame at the centre of the
i-th of n equal slices of the (time-ordered) training frames. The latent is the posterior mean (training frames).
Ground truth = image * mask + background * (1 - mask) at full resolution, then area-resized when
`FitConfig.val_scale` < 1 (the camera is scaled to match). The bbox region is Neural Body's: the posed mesh's 3D box
grown by 5 cm, projected (avatarctl.evaluate.protocols.bbox_region).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from avatarctl.body.base import BodyModel
from avatarctl.evaluate.metrics import metric_settings, psnr
from avatarctl.evaluate.protocols import bbox_region
from avatarctl.fit.conditioning import make_conditioning, time_stamps
from avatarctl.io.project_io import ProjectCapture
from avatarctl.geometry.cameras import Camera
from avatarctl.render.engine import render_view


@dataclass(frozen=True)
class ValPair:
    view: str
    frame: int


def choose_val_pairs(test_views: list[str], train_frames: list[int], n: int) -> list[ValPair]:
    """A fixed, spread-out set of n (held-out view, training frame) pairs; empty without held-out views."""
    frames = sorted(int(f) for f in train_frames)
    if n <= 0 or not test_views or not frames:
        return []
    n = min(n, len(frames) * len(test_views))
    return [ValPair(view=test_views[i % len(test_views)],
                    frame=frames[min(len(frames) - 1, int((i + 0.5) * len(frames) / n))]) for i in range(n)]


@dataclass(frozen=True)
class _Prepared:
    pair: ValPair
    camera: Camera  # scaled pinhole camera
    gt: np.ndarray  # [H, W, 3] float32
    region: np.ndarray  # [H, W] bool, bbox protocol


class Validator:
    """Renders the fixed pairs and scores them; ground truth and regions are prepared once."""

    def __init__(self, capture: ProjectCapture, body: BodyModel, pairs: list[ValPair], train_frames: list[int],
                 background: tuple[float, float, float], scale: float = 1.0):
        import cv2

        self.pairs = pairs
        self.background = background
        self.scale = float(scale)
        frames = sorted({p.frame for p in pairs})
        posed = body.pose(capture.motion.select(capture.motion.rows_for(frames)))
        self._slot = {f: i for i, f in enumerate(frames)}
        time_, ids = time_stamps(frames, train_frames, are_training=True)
        self._cond_parts = (posed.joint_transforms, posed.pose_features, time_, ids)
        bg = np.asarray(background, dtype=np.float32)
        self._prepared: list[_Prepared] = []
        for p in pairs:
            cam = capture.cameras[p.view]
            img = capture.image(p.view, p.frame).astype(np.float32) / 255.0
            m = capture.mask(p.view, p.frame).astype(np.float32)[..., None]
            gt = img * m + bg * (1.0 - m)
            if scale < 1.0:
                cam = cam.scaled(scale)
                gt = cv2.resize(gt, (cam.width, cam.height), interpolation=cv2.INTER_AREA)
            verts = posed.vertices[self._slot[p.frame]].detach().cpu().numpy()
            self._prepared.append(_Prepared(p, cam, gt.astype(np.float32), bbox_region(cam, verts).mask))

    def run(self, model) -> dict[str, Any]:
        """{"psnr": mean dB, "pairs": [{"view", "frame", "psnr"}], "protocol": "bbox", "seconds", ...}."""
        t0 = time.perf_counter()
        device = next(model.parameters()).device
        was_training = model.training
        model.eval()
        results = []
        try:
            with torch.no_grad():
                state = model.node_state(make_conditioning(*self._cond_parts, device=device), mode="mean")
                for prep in self._prepared:
                    view = render_view(model, state, self._slot[prep.pair.frame], prep.camera, self.background,
                                       pixel_mask=prep.region)
                    results.append({"view": prep.pair.view, "frame": prep.pair.frame,
                                    "psnr": psnr(view.rgb, prep.gt, prep.region)})
        finally:
            model.train(was_training)
        return {"psnr": float(np.mean([r["psnr"] for r in results])) if results else None, "pairs": results,
                "protocol": "bbox", "latent": "mean", "scale": self.scale, "settings": metric_settings(),
                "seconds": time.perf_counter() - t0}
