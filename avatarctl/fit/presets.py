"""The presets of `avatarctl fit`, stated once: each is its changes from the class defaults of `FitConfig` and
`ModelConfig`, which are the paper's (supplement) settings, so `paper` changes nothing. `fit.config.preset(name)`
builds the config; `avatarctl fit --help` (`preset_help`) and docs/fit.md's table (`presets_markdown`, checked by
tests/test_fit.py) are made from this table. Plain data, no torch: the CLI reads it at start-up.

"auto" (`model.hull.nodes`, `model.pose_refine.enabled`, `model.cvae_width`, `model.track_refine.enabled`,
`model.gaussians.mask_border_px`) is
decided from the capture at fit start (`fit.loop.decide_auto`, fit/hull_nodes.py, `fit.loop._decide_hull`).
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

_CPU_FIT: dict[str, Any] = {"iters": 20_000, "log_every": 25, "checkpoint_every": 1000, "val_every": 1000,
                            "val_scale": 0.5}
# the ray-marched fields' batch: 512 rays gave more rays/s than 1024 on a shared 2-core machine (~530 vs ~360)
_CPU_MLP_FIT: dict[str, Any] = {**_CPU_FIT, "rays_per_batch": 512}
# the Gaussian fields' own changes (the MLP widths, ray samples and empty-space skipping do nothing for them)
_CPU_GAUSSIAN_MODEL: dict[str, Any] = {k: v for k, v in _CPU_MODEL.items()
                                       if k not in ("node_width", "node_depth", "feature_dim", "head_width",
                                                    "occupancy")}

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
                "width (the paper's 128 from two training views per frame, 32 from one) decided from the capture, a "
                "colour transform per training camera, the training frames' mean latent for novel poses, garment "
                "tracking when there is a loose garment (from 4 training views on, 256 nodes, half of them on it, their "
                "placement corrected per frame, the frames the tracker loses rescued), the held-out frames posed "
                "by the avatar's silhouette after "
                "the fit where the fits are estimated, the masks' outline left out of the image loss where the masks "
                "are estimated (from two training views on); 20k iterations, validation on half-size images every 1000 steps",
        # garment tracking where hull nodes find a loose garment (fit/garment_track.py): synth small, 15 min, two seeds,
        # +0.18 / +0.25 dB held-out and +0.06 / +0.34 novel poses; skipped on tight captures (docs/fit.md); the frames
        # it loses rescued (garment_track.rescue): the same, +0.33 / +0.52 dB held-out, novel poses level
        # the held-out frames posed against the training views' masks after the fit (fit/held_out_poses.py), where
        # pose refinement is on: synth phone, 300 s, the plain held-out figure +4 dB (docs/fit.md)
        fit={**_CPU_FIT, "track": True, "track_rescue": True, "held_out_poses": 80},
        # the cVAE's width from the views (model/config.py CVAE_AUTO_WIDTHS): 128 is +0.15-0.32 dB on the multi-view
        # captures, 32 ahead on a monocular one (docs/fit.md "The cVAE at the paper's width"); the camera colour
        # transforms: +0.38 dB on synth realistic, +0.03 on its clean twin (docs/fit.md deviations)
        # with the garment tracked from 4 views or more, 256 nodes of which 128 on the garment (96 Gaussians each, the
        # same total): synth small, 15 min, +0.15 dB held-out on both seeds (fit.loop.TRACKED_NODES_MIN_VIEWS); with
        # it, the tracked nodes' per-frame corrections (model/track_refine.py; docs/fit.md "Garment tracking")
        # the estimated masks' outline (1 px either side) left out of the image loss from two training views on: synth
        # realistic, 300 s, +0.06 / +0.10 dB held-out; a phone video level (docs/fit.md "The masks' outline left out")
        model={**_CPU_GAUSSIAN_MODEL, "field": "gaussians", "cvae_width": "auto", "colour": {"enabled": True},
               "hull": {"nodes": "auto", "tracked_nodes": 256}, "track_refine": {"enabled": "auto"},
               "gaussians": {"mask_border_px": "auto"}}),
    "cpu-mlp": Preset(
        meant_for="a 2-core CPU, with the paper's MLP fields (the cpu preset until 2026-11-27; `reproduce` fits it)",
        summary="narrow networks (node 2 x 32 -> 32, heads 64, cVAE 32), empty-space skipping, hull nodes and pose "
                "refinement decided from the capture, the training frames' mean latent for novel poses; 512 rays "
                "over 4 images per step, 20k iterations, validation on half-size images every 1000 steps",
        fit=_CPU_MLP_FIT,
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

# Every key `--set` takes, stated once: key -> (the local fields it acts on: "any" | "mlp" | "gaussians", what it is).
# A key is here when it is one of the paper's hyperparameters, a preset changes it, or it is a knob the docs teach
# (the budget, the logging, a deviation's switch); docs/fit.md's knob table is made from this (`knobs_markdown`).
# Every other config field is a fixed setting: recorded in fit/config.json, changed only from Python
# (`FitConfig` / `ModelConfig.with_`, e.g. an experiment), refused by `--set`. A knob that does nothing for the
# selected field (model.field) is refused too, and no preset of that field writes it.
KNOBS: dict[str, tuple[str, str]] = {
    # the run
    "iters": ("any", "total optimisation steps (the paper: 300k)"),
    "time_budget_s": ("any", "stop after this many seconds of training, like Ctrl-C (0 = none)"),
    "seed": ("any", "initialisation, sampling and noise"),
    "snapshot_at_s": ("any", "extra checkpoints after these seconds of training (e.g. 120,300)"),
    "amp": ("any", "bfloat16 autocast on CUDA"),
    "cache_mb": ("any", "RAM budget of the cropped-frame cache"),
    "log_every": ("any", "steps between fit/log.jsonl records"),
    "checkpoint_every": ("any", "steps between checkpoints"),
    "keep_checkpoints": ("any", "step checkpoints kept besides latest.pt"),
    "val_every": ("any", "steps between held-out-view validations (0: only at the end)"),
    "val_pairs": ("any", "(held-out view, training frame) pairs per validation (0: none)"),
    "val_scale": ("any", "image scale of the validation renders"),
    "track": ("any", "garment tracking before the fit: hull nodes placed by the tracked cloth (deviation)"),
    "track_rescue": ("any", "with track: frames the tracker lost followed by a second surface built where the "
                            "garment is most spread (deviation)"),
    "held_out_poses": ("gaussians", "steps posing each held-out frame against the training views' masks after "
                                    "the fit, where the fits are estimated (deviation; 0: none)"),
    # the batch and the optimiser (the paper's)
    "images_per_batch": ("any", "images per step (the paper: 4)"),
    "rays_per_batch": ("mlp", "rays per step over those images (the paper: 2048)"),
    "box_fraction": ("mlp", "share of the rays drawn inside the projected body box (deviation, 0.9)"),
    "background": ("any", "the colour the target is composited over and the avatar rendered over"),
    "lr": ("any", "Adam's learning rate (the paper: 5e-4)"),
    "lr_decay_every": ("any", "iterations per decay period (the paper: 20k)"),
    "lr_decay_factor": ("any", "decay per period (deviation: 0.5; the paper gives none; 1 = off)"),
    # the model: the paper's hyperparameters
    "model.num_nodes": ("any", "N nodes (Sec. 3.1)"),
    "model.sigma": ("any", "Eq. 6 Gaussian width, metres"),
    "model.eps": ("any", "Eq. 6 truncation"),
    "model.embed_dim": ("any", "dim of the detail embedding e_i"),
    "model.latent_dim": ("any", "dim of the cVAE latent z_i"),
    "model.pe_coords": ("mlp", "positional-encoding frequencies of the local coordinates"),
    "model.pe_views": ("mlp", "positional-encoding frequencies of the view direction"),
    "model.pe_time": ("any", "positional-encoding frequencies of the time stamp (cVAE)"),
    "model.lambda_rec": ("any", "Eq. 11 weight of the reconstruction term"),
    "model.lambda_trans": ("any", "Eq. 11 weight of L_trans"),
    "model.lambda_ebd": ("any", "Eq. 11 weight of L_ebd"),
    "model.lambda_kl": ("any", "Eq. 11 weight of the KL term"),
    "model.rec_reduction": ("mlp", "Eq. 12 as written (sum over rays) or the mean"),
    # the model: what the presets change
    "model.field": ("any", "the local fields: mlp (the paper's) or gaussians (deviation)"),
    "model.node_width": ("mlp", "F_i hidden channels"),
    "model.node_depth": ("mlp", "F_i hidden layers"),
    "model.feature_dim": ("mlp", "F_i output feature"),
    "model.head_width": ("mlp", "hidden channels of the heads G and H"),
    "model.samples_per_ray": ("mlp", "uniform samples per ray"),
    "model.cvae_width": ("any", "the per-node cVAE's hidden channels, or auto (from the training views)"),
    "model.occupancy.enabled": ("mlp", "empty-space skipping (deviation)"),
    "model.hull.nodes": ("any", "nodes off the body: K, 0 or auto (deviation)"),
    "model.hull.tracked_nodes": ("any", "with the garment tracked from 4 views or more: N in all, half off the body, "
                                        "the Gaussians per node scaled to keep their total (0: N as set; deviation)"),
    "model.novel_latent": ("any", "z of novel poses: zero (the paper) or train_mean (deviation)"),
    "model.track_refine.enabled": ("any", "with the tracked garment: its nodes' placement corrected per frame, "
                                          "learned with the avatar: true, false or auto (deviation)"),
    "model.track_free": ("any", "with track: the share of training frames a step places the paper's way (deviation)"),
    "model.pose_refine.enabled": ("any", "per-frame body-pose refinement: true, false or auto (deviation)"),
    "model.colour.enabled": ("any", "a colour transform per training camera, learned with the avatar (deviation)"),
    # the Gaussian fields' knobs the docs teach (each a measured choice against 3DGS's)
    "model.gaussians.per_node": ("gaussians", "K Gaussians per node (memory and speed against detail)"),
    "model.gaussians.low_pass": ("gaussians", "px^2 added to every splat's 2D covariance (3DGS: 0.3)"),
    "model.gaussians.shading": ("gaussians", "irradiance (shading under fixed lights) or none"),
    "model.gaussians.lambda_ssim": ("gaussians", "D-SSIM weight of the image loss (3DGS: 0.2)"),
    "model.gaussians.mask_border_px": ("gaussians", "pixels either side of each mask's outline left out of the image "
                                                    "loss: a number or auto (deviation)"),
    "model.gaussians.sh_degree": ("gaussians", "spherical-harmonic degree of the colours (0 or 1)"),
}
FIELD_NAMES = {"mlp": "the MLP fields (model.field=mlp)", "gaussians": "the Gaussian fields (model.field=gaussians)"}
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


def knobs_markdown() -> str:
    """docs/fit.md's knob table, from `KNOBS` (tests/test_fit.py checks that the docs hold it verbatim)."""
    rows = ["| `--set` key | acts on | what it is |", "| --- | --- | --- |"]
    rows += [f"| `{key}` | {'both fields' if on == 'any' else on} | {what} |" for key, (on, what) in KNOBS.items()]
    return "\n".join(rows)


def _md_value(v: Any) -> str:
    return str(v).lower() if isinstance(v, bool) else str(v)
