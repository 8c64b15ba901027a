"""The presets of `avatarctl fit`, stated once: each is its changes from the class defaults of `FitConfig` and
`ModelConfig`, which are the paper's (supplement) settings, so `paper` changes nothing. `fit.config.preset(name)`
builds the config; `avatarctl fit --help` (`preset_help`) and docs/fit.md's table (`presets_markdown`, checked by
tests/test_fit.py) are made from this table. Plain data, no torch: the CLI reads it at start-up.

"auto" (`model.hull.nodes`, `model.pose_refine.enabled`, `model.cvae_width`) is decided from the capture at fit
start (`fit.loop.decide_auto`, fit/hull_nodes.py).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Preset:
    """A named starting point: changes from the class defaults (the paper's settings)."""

    meant_for: str
    summary: str  # what it is, in a few words (for --help and docs/fit.md)
    fit: dict[str, Any]  # FitConfig fields that differ from the defaults
    model: dict[str, Any]  # ModelConfig fields that differ from the defaults (a sub-config: a dict of its fields)


_CPU_MODEL: dict[str, Any] = {
    # narrow networks: a step with a few hundred rays takes well under a second on 2 CPU cores
    "node_width": 32, "node_depth": 2, "feature_dim": 32, "head_width": 64, "cvae_width": 32,
    # empty-space skipping (model/occupancy.py): same images, ~20 % more steps per second (docs/fit.md)
    "occupancy": {"enabled": True},
    # hull nodes decided from the masks (fit/hull_nodes.py): +0.4 dB on the skirt capture, the paper's placement on
    # tight clothing (docs/experiments/hull_auto_2026-11-25)
    "hull": {"nodes": "auto"},
    # z of novel poses = the mean posterior mean of the training frames (model/cvae.py): +0.08 / +0.15 dB box and
    # +0.3 / +0.4 dB body on synth small's novel poses, training frames unchanged (docs/experiments/garment_latent_...)
    "novel_latent": "train_mean",
    # pose refinement where the body fits are not ground truth (model/pose_refine.py; docs/fit.md "Pose refinement")
    "pose_refine": {"enabled": "auto"},
}

# 512 rays gave more rays/s than 1024 on a shared 2-core machine (~530 vs ~360)
_CPU_FIT: dict[str, Any] = {"iters": 20_000, "rays_per_batch": 512, "log_every": 25, "checkpoint_every": 1000,
                            "val_every": 1000, "val_scale": 0.5}

# Every preset, stated once (docs/fit.md's table and --help are made from this).
PRESETS: dict[str, Preset] = {
    "paper": Preset(
        meant_for="a GPU; the supplement's settings",
        summary="the supplement: N = 128 nodes, widths 128, 2048 rays over 4 images per step, 64 samples per ray, "
                "300k iterations",
        fit={}, model={}),
    "cpu": Preset(
        meant_for="a 2-core CPU (or a GPU)",
        summary="the structured local Gaussian fields (model.field=gaussians: 192 Gaussians per node, rasterized, "
                "trained on 4 whole image crops per step; docs/fit.md), hull nodes, pose refinement and the cVAE's "
                "width (the paper's 128 from two training views per frame, 32 from one) decided from the capture, the "
                "training frames' mean latent for novel poses; 20k iterations, validation on half-size images every "
                "1000 steps",
        fit=_CPU_FIT,
        # the cVAE's width from the views (model/config.py CVAE_AUTO_WIDTHS): 128 is +0.15-0.32 dB on the multi-view
        # captures, 32 ahead on a monocular one (docs/fit.md "The cVAE at the paper's width")
        model={**_CPU_MODEL, "field": "gaussians", "cvae_width": "auto"}),
    "cpu-mlp": Preset(
        meant_for="a 2-core CPU, with the paper's MLP fields (the cpu preset until 2026-11-27; `reproduce` fits it)",
        summary="narrow networks (node 2 x 32 -> 32, heads 64, cVAE 32), empty-space skipping, hull nodes and pose "
                "refinement decided from the capture, the training frames' mean latent for novel poses; 512 rays "
                "over 4 images per step, 20k iterations, validation on half-size images every 1000 steps",
        fit=_CPU_FIT,
        model=_CPU_MODEL),
    "micro": Preset(
        meant_for="CI smoke tests only; learns nothing useful",
        summary="the cpu-mlp model with 32 nodes, all on the surface, 16 samples per ray; 128 rays over 2 images, "
                "50 iterations, no validation during training",
        fit={"iters": 50, "rays_per_batch": 128, "images_per_batch": 2, "log_every": 10, "checkpoint_every": 50,
             "val_every": 0, "val_pairs": 1, "val_scale": 0.5},
        model={**_CPU_MODEL, "num_nodes": 32, "samples_per_ray": 16, "hull": {"nodes": 0}}),
}
DEFAULT_PRESET = "cpu"  # what `avatarctl fit` uses without --preset
ALIASES = {"gaussians": "cpu"}  # old preset names still read (the cpu preset was "gaussians" until 2026-11-27)


def preset_help() -> str:
    """`--preset`'s help text, from `PRESETS`."""
    parts = [f"'{name}' ({p.meant_for})" for name, p in PRESETS.items()]
    return f"Starting point: {', '.join(parts)}; docs/fit.md lists what each sets. Default: {DEFAULT_PRESET}."


def presets_markdown() -> str:
    """docs/fit.md's preset table, from `PRESETS` (tests/test_fit.py checks that the docs hold it verbatim)."""
    rows = ["| preset | what it is | meant for | changes from the defaults (`FitConfig()`, `ModelConfig()`) |",
            "| --- | --- | --- | --- |"]
    for name, p in PRESETS.items():
        changes = [f"`{k}={_md_value(v)}`" for k, v in p.fit.items()]
        for k, v in p.model.items():
            if isinstance(v, dict):
                changes += [f"`model.{k}.{kk}={_md_value(vv)}`" for kk, vv in v.items()]
            else:
                changes.append(f"`model.{k}={_md_value(v)}`")
        default = " (default)" if name == DEFAULT_PRESET else ""
        rows.append(f"| `{name}`{default} | {p.summary} | {p.meant_for} | {', '.join(changes) or 'none'} |")
    return "\n".join(rows)


def _md_value(v: Any) -> str:
    return str(v).lower() if isinstance(v, bool) else str(v)
