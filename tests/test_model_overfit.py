"""Overfitting test: the full model (cVAE posterior, sparse fields, jittered sampling, Eq. 11 loss) learns a fixed
target image of 256 rays of an analytic normal-coloured sphere (r = 0.25 m) inside the node shell of a toy
2-joint sphere body, over a white background, with Adam at lr 1e-3 and the paper's loss balance (L_rec summed,
Eq. 12). It runs on one thread: with 2 threads the reductions' order varies run to run and the end PSNR varied
between 29.0 and 30.0 dB (seen in the suite); on one thread it is 31.31 dB every run. Measured (1 thread): 11.2 dB
at start, 19.4 dB after 50 steps, 27.0 after 100, 31.3 after 150 (about 19 s). We assert > 30 dB after 150 steps.
(At lr 5e-3 the node translations run away, trans ~16 m^2, and it stalls near 26 dB.)"""

from __future__ import annotations

import math

import torch

from avatarctl.fit.config import preset
from avatarctl.model import FrameConditioning, SlrfAvatar
from avatarctl.body.toy import sphere_template, toy_joint_transforms
from avatarctl.geometry.rays import RayBatch


def sphere_scene(side: int = 16) -> tuple[RayBatch, torch.Tensor]:
    ys, xs = torch.meshgrid(torch.linspace(-0.4, 0.4, side), torch.linspace(-0.4, 0.4, side), indexing="ij")
    o = torch.stack([xs.reshape(-1), torch.full((side * side,), -2.0), ys.reshape(-1)], -1)
    d = torch.tensor([0.0, 1.0, 0.0]).expand_as(o).contiguous()
    b = (o * d).sum(-1)
    disc = b * b - ((o * o).sum(-1) - 0.25 ** 2)
    t = -b - torch.sqrt(disc.clamp_min(0))
    normal = (o + t[:, None] * d) / 0.25
    target = torch.where((disc > 0)[:, None], 0.5 + 0.5 * normal, torch.ones(1, 3))
    return RayBatch(o, d, torch.zeros(len(o), dtype=torch.long)), target


def test_overfit_fixed_image_reaches_30db():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # multi-threaded reductions vary run to run (29.0-30.0 dB seen at 2 threads)
    try:
        _overfit()
    finally:
        torch.set_num_threads(threads)


def _overfit() -> None:
    torch.manual_seed(0)
    g = torch.Generator().manual_seed(0)
    rb, target = sphere_scene()
    model = SlrfAvatar(preset("cpu-mlp").model.with_(num_nodes=32, samples_per_ray=32,
                                                 pose_refine={"enabled": False}),
                       sphere_template(400),
                       num_frames=1)
    M, feats = toy_joint_transforms(torch.zeros(1))
    cond = FrameConditioning(M, feats, torch.zeros(1), torch.zeros(1, dtype=torch.long))
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    bg = torch.ones(3)

    def psnr() -> float:
        with torch.no_grad():
            out = model.render(rb, model.node_state(cond, "mean"), bg)
        return -10 * math.log10(float(((out.rgb - target) ** 2).mean()))

    start = psnr()
    for _ in range(150):
        st = model.node_state(cond, "posterior", g)
        out = model.render(rb, st, bg, jitter=True, generator=g)
        loss = model.losses(out, target, st)
        opt.zero_grad()
        loss.total.backward()
        opt.step()
    end = psnr()
    assert start < 15.0
    assert end > 30.0, f"PSNR {start:.1f} -> {end:.1f} dB"
