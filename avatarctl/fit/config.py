"""`FitConfig`: everything that decides how an avatar is trained, resolved once and saved as `fit/config.json`.

Resolution order (`resolve_fit_config`): preset -> `--ablation` switches -> `--iters` / `--seed` -> `--set key=value`
overrides. Keys of `--set` are the knobs (`fit.presets.KNOBS`: `FitConfig` field names, `model.<ModelConfig field>`
or `model.<group>.<field>`); an unknown key is an `InputError` naming the closest knobs (a typo never silently falls
back to a default), a fixed setting or a knob that does nothing for the selected local fields is refused in one line.

Defaults, one rule for both configs: the class defaults of `FitConfig` and `ModelConfig` are the paper's
(supplement) settings, so `FitConfig()` is the `paper` preset. Every other preset is a named set of changes from them,
stated once in `PRESETS` (avatarctl/fit/presets.py); `avatarctl fit --help` (`preset_help`) and the table in
docs/fit.md (`presets_markdown`, checked by tests/test_fit.py) are made from it. The CLI's default preset is
`DEFAULT_PRESET` ("cpu"). A default that depends on the capture is a value "auto" in the config (`model.hull.nodes`,
`model.pose_refine.enabled`, `model.cvae_width`), decided at fit start; for pose refinement and the cVAE's width the
decision replaces "auto" in the saved config.

Training target (stated convention): real captures have real backgrounds, so the target of a ray is the masked
image composited over a fixed `background` colour (black by default: rgb * mask + background * (1 - mask)), and
the model renders over the same colour.

Deviations from the paper (named, switchable):
- `lr_decay_factor` = 0.5 per `lr_decay_every` = 20k iterations: the paper says the rate "decays exponentially every
  20k iterations" without the factor. The decay is continuous (lr0 * factor ** (step / every)); set
  `lr_decay_factor=1` to switch it off.
- `box_fraction` = 0.9: 90% of each image's rays are drawn uniformly among the pixels inside the projection of the
  posed body's 3D bounding box grown by `crop_pad` metres, 10% uniformly over the whole image (Neural Body's
  protocol samples inside the box; the paper gives no split).
"""

from __future__ import annotations

import difflib
import math
from dataclasses import asdict, dataclass, field, fields, is_dataclass, replace
from typing import Any

from avatarctl.errors import InputError
from avatarctl.lists import split_list
from avatarctl.fit.presets import ALIASES, DEFAULT_PRESET, FIELD_NAMES, KNOBS, PRESETS
from avatarctl.model.config import AUTO, LEGACY_KEYS, ModelConfig, nest_legacy_keys

SCHEMA_VERSION = 2  # 2: lr_pose / pose_refine_start moved into model.pose_refine (1: read by `from_json`)
# Keys of saved configs that are gone, now fixed (docs/fit.md "Tried and removed"): key -> (the value the code keeps,
# the last commit that had the key). Dropped on reading when they hold that value (None: any value, an option of
# removed code), else a one-line error naming the commit.
_REMOVED_KEYS: dict[str, tuple[Any, str]] = {
    "lr_grid": (None, "0081142"),  # the grid field's rate (issue 28 removed that field)
    "mask_dilate_px": (4, "0081142"),  # the dilation of the mask that mask_fraction's rays were drawn from
    "jitter": (True, "0081142"),  # stratified jitter of the training samples: always
    "grad_clip": (0.0, "0081142"),  # no gradient clipping (the paper clips none)
    # focused sampling on the dilated mask: +0.26 dB at equal steps for 1.5x the time per step, 0 in every preset
    # (issue 49: a switch no preset uses and that measured worse at equal time goes)
    "mask_fraction": (0.0, "3519fa5"),
    # the crops over ingest's estimated background plates: floaters over the plate (docs/fit.md "Tried and removed")
    "plates": (False, "4ade4b6"),
}




# --ablation name -> ModelConfig changes (paper Sec. 5 ablations + the pose-only LBS baseline)
ABLATIONS: dict[str, dict[str, Any]] = {
    "no-delta-n": {"use_delta_n": False},
    "no-embedding": {"use_embedding": False},
    "deterministic": {"latent": "deterministic"},
    "per-frame-latent": {"latent": "per_frame"},
    "lbs-baseline": {"variant": "lbs_baseline", "field": "mlp"},  # the pose-only baseline is a canonical MLP
}


@dataclass(frozen=True)
class FitConfig:
    """How to train one avatar. Immutable; validated on construction; JSON round-trips (`to_json` / `from_json`).
    The defaults are the paper's settings (the `paper` preset); see `PRESETS`."""

    preset: str = "paper"  # the preset this config started from (informational)
    iters: int = 300_000  # total optimisation steps (the paper's ZJU-MoCap count)
    seed: int = 0  # seeds the model initialisation, the ray sampler and the latent / jitter noise
    # batch (paper: 2048 rays per batch, batch size 4)
    rays_per_batch: int = 2048  # rays per step, over all images of the batch
    images_per_batch: int = 4  # (training frame, training view) images per step; each gets its own frame slot
    box_fraction: float = 0.9  # share of rays drawn inside the projected body box (the rest: whole image)
    crop_pad: float = 0.25  # metres the posed body's 3D box is grown by, for the crop and the "inside" region
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)  # target = rgb * mask + background * (1 - mask)
    # optimiser (paper: Adam lr 5e-4, betas 0.9 / 0.999, exponential decay every 20k iterations)
    lr: float = 5e-4
    adam_beta1: float = 0.9
    adam_beta2: float = 0.999
    lr_decay_every: int = 20_000  # iterations per decay period
    lr_decay_factor: float = 0.5  # deviation: the factor is not given in the paper (1.0 switches decay off)
    amp: bool = False  # bfloat16 autocast on CUDA (ignored on CPU)
    time_budget_s: float = 0.0  # stop (checkpoint, validate, record) after this many seconds of training; 0 = none
    snapshot_at_s: tuple[float, ...] = ()  # also save checkpoints/snapshot_<s>s.pt after these seconds of training
    # data loading
    cache_mb: int = 2048  # RAM budget of the LRU cache of cropped frames
    # bookkeeping
    log_every: int = 100  # steps between fit/log.jsonl records
    checkpoint_every: int = 5000  # steps between checkpoints (and always at the end / on Ctrl-C)
    keep_checkpoints: int = 3  # step_*.pt files kept (latest.pt always)
    val_every: int = 5000  # steps between held-out-view validations, 0 = only at the end
    val_pairs: int = 2  # fixed (held-out view, training frame) pairs rendered per validation, 0 = none
    val_scale: float = 1.0  # image scale for validation renders (bbox-protocol PSNR on the scaled images)
    # garment tracking (fit/garment_track.py, a deviation): a fresh fit with hull nodes (a loose garment) and two
    # training views or more first tracks the garment's surface through the training frames and places the hull
    # nodes by it on those frames; its time counts towards time_budget_s
    track: bool = False
    # with track: where the tracker lost the garment (a twirl), a second surface built where it is most spread carries
    # the first over the lost frames (garment_track.rescue, a deviation; on in the cpu preset)
    track_rescue: bool = False
    # the held-out frames posed after training (fit/held_out_poses.py, a deviation): where pose refinement is on
    # (estimated fits), each of the capture's test frames that is not a training frame gets this many Adam steps of
    # its pose against the training views' masks, the avatar frozen (Gaussian fields); 0 = none; after the budget
    held_out_poses: int = 0
    ablations: tuple[str, ...] = ()  # informational: which --ablation switches made `model`
    model: ModelConfig = field(default_factory=ModelConfig)

    def __post_init__(self) -> None:
        object.__setattr__(self, "background", tuple(float(c) for c in self.background))
        object.__setattr__(self, "ablations", tuple(str(a) for a in self.ablations))
        object.__setattr__(self, "snapshot_at_s", tuple(sorted(float(t) for t in self.snapshot_at_s)))

        def need(ok: bool, msg: str) -> None:
            if not ok:
                raise InputError(f"invalid fit config: {msg}", fix="check --set / --preset values (see docs/fit.md)")

        for name in ("iters", "rays_per_batch", "images_per_batch", "lr_decay_every", "cache_mb", "log_every",
                     "checkpoint_every", "keep_checkpoints"):
            v = getattr(self, name)
            need(isinstance(v, int) and not isinstance(v, bool) and v > 0, f"{name} must be a positive int, got {v!r}")
        for name in ("val_every", "val_pairs", "seed", "held_out_poses"):
            v = getattr(self, name)
            need(isinstance(v, int) and not isinstance(v, bool) and v >= 0, f"{name} must be an int >= 0, got {v!r}")
        need(self.preset in PRESETS, f"preset must be one of {tuple(PRESETS)}, got {self.preset!r}")
        need(self.rays_per_batch >= self.images_per_batch,
             f"rays_per_batch ({self.rays_per_batch}) must be >= images_per_batch ({self.images_per_batch})")
        need(0.0 <= self.box_fraction <= 1.0, f"box_fraction must be in [0, 1], got {self.box_fraction}")
        need(self.crop_pad >= 0.0, f"crop_pad must be >= 0 metres, got {self.crop_pad}")
        need(len(self.background) == 3 and all(0.0 <= c <= 1.0 for c in self.background),
             f"background must be 3 values in [0, 1], got {self.background}")
        need(self.lr > 0 and math.isfinite(self.lr), f"lr must be > 0, got {self.lr}")
        need(0.0 <= self.adam_beta1 < 1.0 and 0.0 <= self.adam_beta2 < 1.0, "adam betas must be in [0, 1)")
        need(0.0 < self.lr_decay_factor <= 1.0, f"lr_decay_factor must be in (0, 1], got {self.lr_decay_factor}")
        need(self.time_budget_s >= 0.0, f"time_budget_s must be >= 0 seconds, got {self.time_budget_s}")
        need(all(t > 0 for t in self.snapshot_at_s), f"snapshot_at_s must be > 0 seconds, got {self.snapshot_at_s}")
        need(0.0 < self.val_scale <= 1.0, f"val_scale must be in (0, 1], got {self.val_scale}")
        for a in self.ablations:
            need(a in ABLATIONS, f"unknown ablation {a!r}; expected some of {sorted(ABLATIONS)}")
        need(isinstance(self.model, ModelConfig), "model must be a ModelConfig")

    # ---- JSON ---------------------------------------------------------------------------------------------------
    def to_json(self) -> dict[str, Any]:
        d = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "model"}
        d["background"] = list(self.background)
        d["ablations"] = list(self.ablations)
        d["snapshot_at_s"] = list(self.snapshot_at_s)
        return {"schema_version": SCHEMA_VERSION, **d, "model": self.model.to_json()}

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> "FitConfig":
        """Inverse of `to_json`; unknown keys are an error. Reads schema_version 1 too (`lr_pose`,
        `pose_refine_start` at the top; the model's flat keys: `ModelConfig.from_json`)."""
        d = dict(d)
        version = d.pop("schema_version", SCHEMA_VERSION)
        if version not in (1, SCHEMA_VERSION):
            raise InputError(f"fit config schema_version {version} is not supported (expected {SCHEMA_VERSION})",
                             fix="re-run `avatarctl fit` with this avatarctl version")
        for key, (neutral, commit) in _REMOVED_KEYS.items():
            if key in d and d.pop(key) != neutral and neutral is not None:
                raise InputError(f"fit config: {key} was removed (what it set is now fixed: {neutral!r})",
                                 fix=f"fit again, or use avatarctl at commit {commit}")
        if version == 1:
            moved = {LEGACY_KEYS[k][1]: d.pop(k) for k in ("lr_pose", "pose_refine_start") if k in d}
            if moved and "model" in d:  # into model.pose_refine (the model dict is version 1 too)
                model = nest_legacy_keys(d["model"])
                d["model"] = {**model, "pose_refine": {**model.get("pose_refine", {}), **moved}}
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise InputError(f"unknown fit config keys {unknown}", fix=f"known keys: {sorted(known)}")
        try:
            model = ModelConfig.from_json(d.pop("model")) if "model" in d else _OLDEST_MODEL
        except ValueError as e:
            raise InputError(str(e), fix="check the model section of the fit config") from None
        d["preset"] = current_preset_name(str(d.get("preset", "paper")), model.field)
        d["background"] = tuple(d.get("background", (0.0, 0.0, 0.0)))
        d["ablations"] = tuple(d.get("ablations", ()))
        d["snapshot_at_s"] = tuple(d.get("snapshot_at_s", ()))
        return cls(**d, model=model)


def current_preset_name(saved: str, field: str) -> str:
    """The preset a saved config's name means now: configs written before 2026-11-27 called the MLP fields' CPU preset
    "cpu" (now "cpu-mlp") and the Gaussian one "gaussians" (now "cpu"); the name is informational, the saved settings
    are what is used."""
    if saved == "cpu" and field == "mlp":
        return "cpu-mlp"
    return ALIASES.get(saved, saved)


def preset(name: str) -> FitConfig:
    """The named preset (`PRESETS`, or an old name of one: `ALIASES`)."""
    name = ALIASES.get(name, name)
    if name not in PRESETS:
        raise InputError(f"unknown preset {name!r}", fix=f"use one of: {', '.join(PRESETS)}")
    p = PRESETS[name]
    return FitConfig(preset=name, **p.fit, model=ModelConfig().with_(**p.model))


# the model of fit configs written before they held one: the cpu preset of that time, cpu-mlp now (no pose refinement)
_OLDEST_MODEL = ModelConfig().with_(**{**PRESETS["cpu-mlp"].model, "pose_refine": {"enabled": False}})


def parse_ablations(spec: str | None) -> tuple[str, ...]:
    """'no-delta-n,no-embedding' -> ('no-delta-n', 'no-embedding'); unknown names are an `InputError`."""
    if not spec:
        return ()
    names = split_list(spec)
    for n in names:
        if n not in ABLATIONS:
            close = difflib.get_close_matches(n, list(ABLATIONS), n=1)
            hint = f"did you mean {close[0]!r}? " if close else ""
            raise InputError(f"unknown ablation {n!r}", where="--ablation",
                             fix=f"{hint}choose from: {', '.join(ABLATIONS)}")
    latents = [n for n in names if "latent" in ABLATIONS[n]]
    if len(latents) > 1:
        raise InputError(f"ablations {latents} both replace the latent", where="--ablation", fix="pick one of them")
    return tuple(dict.fromkeys(names))


def apply_ablations(cfg: FitConfig, names: tuple[str, ...]) -> FitConfig:
    changes: dict[str, Any] = {}
    for n in names:
        changes.update(ABLATIONS[n])
    return replace(cfg, ablations=tuple(dict.fromkeys(cfg.ablations + names)), model=_model_with(cfg.model, changes))


def _model_with(model: ModelConfig, changes: dict[str, Any]) -> ModelConfig:
    try:
        return model.with_(**changes)
    except ValueError as e:
        raise InputError(str(e), where="--set / --ablation", fix="see docs/fit.md for valid model values") from None


_NOT_SETTABLE = {"ablations": "use --ablation", "model": "use model.<field>=value", "preset": "use --preset"}
_AUTO_KEYS = ("model.hull.nodes", "model.pose_refine.enabled", "model.cvae_width",  # may be "auto": from the capture
              "model.gaussians.mask_border_px")


def _parse_value(key: str, text: str, current: Any) -> Any:
    """Parse `text` to the type of the current value of `key` (bool, int, float, str or tuple of floats); the keys
    of `_AUTO_KEYS` also take "auto"."""
    t = text.strip()
    auto_kind = "bool" if key == "model.pose_refine.enabled" else "int"
    try:
        if key in _AUTO_KEYS:
            if t.lower() == AUTO:
                return AUTO
            current = current if current != AUTO else (False if auto_kind == "bool" else 0)
        if isinstance(current, bool):
            low = t.lower()
            if low in ("1", "true", "yes", "on"):
                return True
            if low in ("0", "false", "no", "off"):
                return False
            raise ValueError(t)
        if isinstance(current, int):
            f = float(t)
            if not f.is_integer():
                raise ValueError(t)
            return int(f)
        if isinstance(current, float):
            return float(t)
        if isinstance(current, tuple):  # tuple of ints or of floats (e.g. snapshot_at_s=120,300)
            conv = int if current and all(isinstance(x, int) for x in current) else float
            return split_list(t, conv)
        return t
    except ValueError:
        kind = f"{auto_kind} or auto" if key in _AUTO_KEYS else type(current).__name__
        example = {"bool": "true|false", "int": "1000", "float": "0.0005", "tuple": "0,0,0",
                   "int or auto": "32|auto", "bool or auto": "true|false|auto"}.get(kind, "text")
        raise InputError(f"cannot read {key}={text!r} as {kind}", where="--set", fix=f"write e.g. {key}={example}") \
            from None


def config_keys() -> list[str]:
    """Every field of the configs as a dotted key: FitConfig fields, `model.<field>` and `model.<sub-config>.<field>`."""
    keys = [f.name for f in fields(FitConfig) if f.name not in _NOT_SETTABLE]
    for f in fields(ModelConfig):
        sub = f.default if is_dataclass(f.default) else None
        keys += [f"model.{f.name}.{g.name}" for g in fields(sub)] if sub is not None else [f"model.{f.name}"]
    return keys


def settable_keys() -> list[str]:
    """Every key `--set` takes: the knobs (`fit.presets.KNOBS`)."""
    return list(KNOBS)


def _check_knob(given: str, key: str) -> None:
    """`key` (`given` as the user wrote it) must be a knob: a one-line error for a fixed setting or an ablation switch."""
    if key in KNOBS:
        return
    if key in _ABLATION_KEYS:
        raise InputError(f"{given!r} is switched by --ablation, not --set", where="--set",
                         fix=f"use --ablation {_ABLATION_KEYS[key]}")
    if key in config_keys():
        raise InputError(f"{given!r} is a fixed setting, not a knob (recorded in fit/config.json)", where="--set",
                         fix="the knobs are listed in docs/fit.md \"Knobs\"; an experiment changes a fixed setting "
                             "from Python (FitRequest.model_settings, ModelConfig.with_)")
    close = difflib.get_close_matches(given, list(KNOBS), n=3)
    hint = f"did you mean {' or '.join(repr(c) for c in close)}? " if close else ""
    raise InputError(f"unknown config key {given!r}", where="--set",
                     fix=f"{hint}the knobs are listed in docs/fit.md \"Knobs\"")


def check_live(keys: list[str], field: str) -> None:
    """Each knob of `keys` must act on the local fields `field` (`KNOBS`): one line naming the first that does not."""
    for key in keys:
        on = KNOBS[key][0]
        if on not in ("any", field):
            raise InputError(f"--set {key} does nothing for {FIELD_NAMES[field]}: it acts on {FIELD_NAMES[on]}",
                             where="--set", fix=f"leave it out, or also set model.field={on}")


def _ablation_switches() -> dict[str, str]:
    """The ModelConfig keys only an ablation switch sets (not knobs) -> the switches that set them (`ABLATIONS`)."""
    out: dict[str, list[str]] = {}
    for name, changes in ABLATIONS.items():
        for field_name in changes:
            if f"model.{field_name}" not in KNOBS:
                out.setdefault(f"model.{field_name}", []).append(name)
    return {k: " or ".join(v) for k, v in out.items()}


_ABLATION_KEYS = _ablation_switches()


def _canonical_key(key: str) -> str:
    """A key of the flat config of schema_version 1 (`model.occ_res`, `lr_pose`, ...) -> its nested key."""
    name = key.removeprefix("model.")
    if name in LEGACY_KEYS and (key.startswith("model.") or name in ("lr_pose", "pose_refine_start")):
        return "model." + ".".join(LEGACY_KEYS[name])
    return key


def apply_overrides(cfg: FitConfig, overrides: list[str]) -> FitConfig:
    """Apply `key=value` overrides. Keys: the knobs (`settable_keys`, e.g. `lr`, `model.gaussians.per_node`); the
    flat keys of older configs (`model.hull_nodes`, `model.occupancy`, ...; `LEGACY_KEYS`) name the same fields. Each
    knob must act on the local fields the result selects (`check_live`)."""
    fit_changes: dict[str, Any] = {}
    model_changes: dict[str, Any] = {}
    sub_changes: dict[str, dict[str, Any]] = {}
    set_keys: list[str] = []
    for item in overrides:
        if "=" not in item:
            raise InputError(f"override {item!r} is not key=value", where="--set", fix="write e.g. --set lr=1e-4")
        given, text = (s.strip() for s in item.split("=", 1))
        if given in _NOT_SETTABLE:
            raise InputError(f"{given!r} cannot be set with --set", where="--set", fix=_NOT_SETTABLE[given])
        key = _canonical_key(given)
        _check_knob(given, key)
        set_keys.append(key)
        parts = key.split(".")
        if len(parts) == 1:
            fit_changes[key] = _parse_value(key, text, getattr(cfg, key))
        elif len(parts) == 2:
            model_changes[parts[1]] = _parse_value(key, text, getattr(cfg.model, parts[1]))
        else:
            sub_changes.setdefault(parts[1], {})[parts[2]] = _parse_value(
                key, text, getattr(getattr(cfg.model, parts[1]), parts[2]))
    model_changes.update(sub_changes)  # dicts of sub-config fields (`ModelConfig.with_`)
    model = _model_with(cfg.model, model_changes) if model_changes else cfg.model
    check_live(set_keys, model.field)
    return replace(cfg, **fit_changes, model=model)


def resolve_fit_config(preset_name: str = DEFAULT_PRESET, ablation: str | None = None, iters: int | None = None,
                       seed: int | None = None, overrides: list[str] | None = None) -> FitConfig:
    """preset -> ablations -> iters / seed -> `--set` overrides (see the module docstring)."""
    cfg = preset(preset_name)
    cfg = apply_ablations(cfg, parse_ablations(ablation))
    if iters is not None:
        cfg = replace(cfg, iters=int(iters))
    if seed is not None:
        cfg = replace(cfg, seed=int(seed))
    return apply_overrides(cfg, list(overrides or []))


def config_summary(cfg: FitConfig) -> dict[str, Any]:
    """A short dict for summaries: the knobs people compare runs by."""
    m = asdict(cfg.model)
    return {"preset": cfg.preset, "iters": cfg.iters, "rays_per_batch": cfg.rays_per_batch,
            "images_per_batch": cfg.images_per_batch, "samples_per_ray": m["samples_per_ray"],
            "num_nodes": m["num_nodes"], "ablations": list(cfg.ablations), "seed": cfg.seed}
