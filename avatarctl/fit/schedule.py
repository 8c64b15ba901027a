"""Optimiser and learning-rate schedule (paper supplement: Adam, lr 5e-4, betas 0.9 / 0.999, exponential decay
every 20k iterations).

The decay factor is not in the paper: `FitConfig.lr_decay_factor` (default 0.5 per `lr_decay_every` = 20k
iterations) is our named deviation. The decay is continuous, lr(step) = lr0 * factor ** (step / every), so the
rate halves over each 20k-iteration period; factor 1 switches it off.
"""

from __future__ import annotations

import torch

from avatarctl.fit.config import FitConfig


def lr_at(cfg: FitConfig, step: int) -> float:
    """The learning rate used for optimisation step `step` (0-based)."""
    return cfg.lr * cfg.lr_decay_factor ** (step / cfg.lr_decay_every)


def make_optimizer(cfg: FitConfig, params) -> torch.optim.Adam:
    """Adam over `params` (tensors, or param groups such as `param_groups` returns)."""
    return torch.optim.Adam(params, lr=cfg.lr, betas=(cfg.adam_beta1, cfg.adam_beta2), fused=True)


def param_groups(cfg: FitConfig, model: torch.nn.Module) -> list[dict]:
    """Adam param groups: the Gaussians' own parameters (`model.field = "gaussians"`) at 3DGS's rates
    (`model.gaussians.lr_*`), the pose-refinement corrections at `cfg.model.pose_refine.lr`, everything else at
    `cfg.lr`, the camera colour transforms at `cfg.model.colour.lr`, the tracked garment's corrections at
    `cfg.model.track_refine.lr` / `lr_rotation`. All follow the same decay."""
    fields = getattr(model, "fields", None)
    refine = getattr(model, "pose_refine", None)
    pose = list(refine.parameters()) if refine is not None else []
    colour_module = getattr(model, "camera_colour", None)
    colour = list(colour_module.parameters()) if colour_module is not None else []
    tracked = getattr(model, "track_refine", None)
    track = [tracked.translation] if tracked is not None else []
    track_rot = [tracked.rotation] if tracked is not None else []
    splats = fields.gaussian_parameters() if hasattr(fields, "gaussian_parameters") else {}
    special = {id(p) for p in pose + colour + track + track_rot + [q for ps in splats.values() for q in ps]}
    rest = [p for p in model.parameters() if id(p) not in special]
    return [{"params": rest}] \
        + [{"params": ps, "lr": getattr(cfg.model.gaussians, name), "name": name} for name, ps in splats.items()] \
        + ([{"params": pose, "lr": cfg.model.pose_refine.lr, "name": "pose"}] if pose else []) \
        + ([{"params": colour, "lr": cfg.model.colour.lr, "name": "colour"}] if colour else []) \
        + ([{"params": track, "lr": cfg.model.track_refine.lr, "name": "track"},
            {"params": track_rot, "lr": cfg.model.track_refine.lr_rotation, "name": "track"}] if track else [])


def make_scheduler(cfg: FitConfig, optimizer: torch.optim.Optimizer) -> torch.optim.lr_scheduler.LambdaLR:
    """Multiplies the base lr by factor ** (step / every); call `.step()` once per optimisation step. The
    pose-refinement groups (named "pose" by `param_groups`) are 0 before `cfg.model.pose_refine.start`, the tracked
    garment's corrections ("track") before `cfg.model.track_refine.start`."""
    factor, every = cfg.lr_decay_factor, cfg.lr_decay_every
    starts = {"pose": cfg.model.pose_refine.start, "track": cfg.model.track_refine.start}

    def decay(step: int) -> float:
        return factor ** (step / every)

    def rule(group: dict):
        start = starts.get(group.get("name"), 0)
        if not start:
            return decay
        return lambda step: decay(step) if step >= start else 0.0

    return torch.optim.lr_scheduler.LambdaLR(optimizer, [rule(g) for g in optimizer.param_groups])
