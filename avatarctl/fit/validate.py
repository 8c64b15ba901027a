"""Held-out-view validation during training: PSNR (bbox protocol) on a small fixed set of
(held-out view, training frame) pairs, through the one metrics module (`avatarctl.evaluate.metrics`).

Pairs (`choose_val_pairs`): the i-th pair takes held-out view i mod V and the training frame at the centre of the
i-th of n equal slices of the (time-ordered) training frames. The latent is the posterior mean (training frames).
Ground truth = image * mask + background * (1 - mask) (`evaluate.protocols.ground_truth`) at full resolution, then
area-resized when `FitConfig.val_scale` < 1 (the camera is scaled to match). The bbox region is Neural Body's: the
posed mesh's 3D box grown by 5 cm, projected (avatarctl.evaluate.protocols.bbox_region).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import torch

from avatarctl.body.base import BodyModel
from avatarctl.evaluate.metrics import metric_settings, psnr
from avatarctl.evaluate.protocols import bbox_region, ground_truth
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
        posed = body.pose(capture.motion.for_frames(frames))
        self._slot = {f: i for i, f in enumerate(frames)}
        time_, ids = time_stamps(frames, train_frames, are_training=True)
        self._cond_parts = (posed.joint_transforms, posed.pose_features, time_, ids)
        bg = np.asarray(background, dtype=np.float32)
        self._prepared: list[_Prepared] = []
        for p in pairs:
            cam = capture.cameras[p.view]
            gt = ground_truth(capture.image(p.view, p.frame), capture.mask(p.view, p.frame), bg)
            if scale < 1.0:
                cam = cam.scaled(scale)
                gt = cv2.resize(gt, (cam.width, cam.height), interpolation=cv2.INTER_AREA)
            verts = posed.vertices[self._slot[p.frame]].detach().cpu().numpy()
            self._prepared.append(_Prepared(p, cam, gt.astype(np.float32), bbox_region(cam, verts).mask))

    def score(self, model) -> "ValidationResult":
        """Render every pair with the posterior-mean latent and score it (PSNR, bbox protocol)."""
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
                    results.append(PairScore(view=prep.pair.view, frame=prep.pair.frame,
                                             psnr=psnr(view.rgb, prep.gt, prep.region)))
        finally:
            model.train(was_training)
        return ValidationResult(psnr=float(np.mean([r.psnr for r in results])) if results else None,
                                pairs=tuple(results), scale=self.scale, settings=metric_settings(),
                                seconds=time.perf_counter() - t0)


@dataclass(frozen=True)
class PairScore:
    view: str
    frame: int
    psnr: float  # dB over the bbox region


@dataclass(frozen=True)
class ValidationResult:
    """One validation: the mean PSNR over the fixed pairs, and each pair's."""

    psnr: float | None  # mean dB; None without pairs
    pairs: tuple[PairScore, ...]
    scale: float  # FitConfig.val_scale
    settings: dict[str, Any]  # metric_settings()
    seconds: float
    protocol: str = "bbox"
    latent: str = "mean"

    def to_json(self) -> dict[str, Any]:
        return {"psnr": self.psnr, "pairs": [asdict(p) for p in self.pairs], "protocol": self.protocol,
                "latent": self.latent, "scale": self.scale, "settings": self.settings, "seconds": self.seconds}

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> "ValidationResult":
        return cls(psnr=None if d["psnr"] is None else float(d["psnr"]),
                   pairs=tuple(PairScore(view=str(p["view"]), frame=int(p["frame"]), psnr=float(p["psnr"]))
                               for p in d["pairs"]),
                   scale=float(d["scale"]), settings=dict(d["settings"]), seconds=float(d["seconds"]),
                   protocol=str(d["protocol"]), latent=str(d["latent"]))
