"""`ModelConfig`: every hyperparameter of the structured local radiance fields (SLRF) model.

Defaults are the supplement's table (N=128, sigma=0.05, eps=0.001, dim e=32, dim z=8, 64 uniform samples per
ray, lambda_rec/trans/ebd/KL = 1 / 0.02 / 0.1 / 1e-5, positional encodings m = 6 / 4 / 12). The network widths are
our choice because the paper's architecture figure (supp. Fig. A) is not available:

- local fields F_i: `node_depth` fully connected ReLU layers of `node_width` channels, then a linear layer to a
  `feature_dim` feature (paper preset 3 x 128 -> 128);
- heads: density H(f) = Linear(f, head_width) -> ReLU -> Linear(1) -> softplus; colour
  G(f, v) = Linear([f, gamma(v)], head_width) -> ReLU -> Linear(head_width // 2) -> ReLU -> Linear(3) -> sigmoid;
- per-node cVAE encoder and decoder: two ReLU layers of `cvae_width` channels each.

The class defaults are the paper's (supplement) settings, here and in `FitConfig` (the `paper` preset); the other
presets (`cpu`, `cpu-mlp`, `micro`) are named sets of changes from them, stated once in `avatarctl/fit/presets.py`
(`PRESETS`).

The options of one part that only matter when it is used sit in small frozen sub-configs: `hull` (`HullConfig`,
nodes off the body), `occupancy` (`OccupancyConfig`, empty-space skipping), `pose_refine` (`PoseRefineConfig`,
per-frame body-pose refinement), `gaussians` (`GaussianConfig`, the Gaussian local fields), `colour` (`ColourConfig`, a
colour transform per training camera), `track_refine` (`TrackRefineConfig`, the tracked garment's per-frame
corrections). Configs written before
they existed (schema_version 1, flat keys such as `occ_res` or `hull_nodes`) are read through `LEGACY_KEYS`.

Choices beyond the paper text (documented, switchable):
- local coordinates p_i (Eq. 4) are divided by sigma before the positional encoding (not a switch: the knob
  `local_coords_in_sigma` that could turn it off was set by nothing and went in issue 30), so the node's support
  (radius sigma*sqrt(-2 ln eps) = 3.7 sigma) spans ~3.7 units and the highest frequency 2^(m-1) = 32 resolves
  ~1 cm; in metres the same encoding would resolve only ~20 cm inside a node.
- `pack_block` (speed, not maths): the supplement packs the valid pairs into one N x max_i(S_i) tensor, which is
  mostly padding when S_i varies a lot between nodes (39-59% fill measured on anny). With `pack_block` = b > 0 each
  node's pairs fill ceil(S_i / b) blocks of b rows and every block carries its node's weights (a gather), so
  padding is < b rows per node. Same outputs and gradients; `pack_block = 0` is the supplement's layout.
- `pose_attention_hops`: the SCANimate-style attention map W (Eq. 8) lets joint k attend to every joint within
  this many hops in the kinematic tree (see `deformer.pose_attention_map`).
- `field = "gaussians"`: structured local Gaussian fields (model/gaussian_field.py), K 3D Gaussians per node,
  rasterized instead of ray-marched; its options live in `GaussianConfig` (`model.gaussians.*`), docs/fit.md.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields, replace
from typing import Any

SCHEMA_VERSION = 2  # 2: hull / occupancy / pose refinement as sub-configs (1: flat keys, read via LEGACY_KEYS)
LATENTS = ("cvae", "deterministic", "per_frame")
VARIANTS = ("slrf", "lbs_baseline")
# local fields F_i: the paper's per-node MLPs | per-node 3D Gaussians rasterized instead of ray-marched
# (model/gaussian_field.py, options in `GaussianConfig`). The per-node feature grids ("grid") were removed in issue 28
# (beaten by the Gaussians at equal wall time; figures in docs/fit.md, "Tried and removed").
FIELDS = ("mlp", "gaussians")
REC_REDUCTIONS = ("sum", "mean")  # Eq. 12 as written (sum over rays) | plain MSE, see model/losses.py
NOVEL_LATENTS = ("zero", "train_mean")  # z of novel poses: the paper's 0 | the mean of mu over the training frames
AUTO = "auto"  # `hull.nodes` / `pose_refine.enabled` / `track_refine.enabled` / `cvae_width`: decided at fit start
# `cvae_width = "auto"`: (one training view per frame, two or more) -> width. The paper's 128 is ahead on every
# multi-view capture measured and behind on the monocular one (docs/fit.md "The cVAE at the paper's width")
CVAE_AUTO_WIDTHS = (32, 128)

# Switches removed after measuring them (docs/fit.md, "Tried and removed"; code at the commit named there). A saved
# config may still hold one: it is dropped on reading when it holds the value the code now has built in (None: any
# value, the key only shaped the initialisation or an option of removed code), else it is a one-line error.
REMOVED_KEYS: dict[str, Any] = {
    "grid_levels": None, "grid_channels": None,  # the grid field (issue 28; its last commit e4ec5be)
    "pe_anneal_steps": 0, "pe_anneal_start": None,  # coarse-to-fine gamma(p) (issue 30, commit 0081142)
    "occ_stop_eps": 0.0,  # early ray termination from the occupancy grids' densities (issue 30, commit 0081142)
    "posterior_logvar_init": None,  # initial log-variance of the cVAE posterior (issue 30, commit 0081142)
    "density_scale": 1.0, "density_shift": 0.0,  # scaled / shifted softplus of the density head (issue 30, 0081142)
    "local_coords_in_sigma": True,  # p_i in units of sigma: set by nothing, now always (issue 30, commit 0081142)
    "lambda_pose_accel": None,  # the pose refinement's smoothness term (removed 2026-11-29: training only)
}


def _check_removed(owner: str, d: dict[str, Any]) -> None:
    """Drop the keys of `REMOVED_KEYS` from `d` (a config read from JSON), or raise when one holds a value that
    changed what the avatar computes."""
    for key, neutral in REMOVED_KEYS.items():
        if key in d:
            value = d.pop(key)
            if neutral is not None and value != neutral:
                raise ValueError(f"{owner}: {key}={value!r} was removed in issue 30 (docs/fit.md, \"Tried and "
                                 f"removed\"); this avatar needs avatarctl at commit 0081142, or a new fit")


def _need_switch(owner: str, v: Any) -> None:
    """A switch decided from the capture: true, false or "auto" (a ValueError naming `owner` otherwise)."""
    if not (isinstance(v, bool) or v == AUTO):
        raise ValueError(f"{owner}: enabled must be true, false or {AUTO!r}, got {v!r}")


def _need_int(owner: str, name: str, v: Any, minimum: int) -> None:
    if not (isinstance(v, int) and not isinstance(v, bool) and v >= minimum):
        raise ValueError(f"{owner}: {name} must be an int >= {minimum}, got {v!r}")


class _SubConfig:
    """Shared by the small frozen sub-configs: JSON with unknown keys rejected, and no truth value (write
    `cfg.occupancy.enabled`, never `if cfg.occupancy`)."""

    def __bool__(self) -> bool:
        raise TypeError(f"{type(self).__name__} has no truth value; test its switch field")

    @classmethod
    def from_json(cls, d: dict[str, Any]):
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"{cls.__name__}: unknown keys {unknown}; known keys are {sorted(known)}")
        return cls(**d)


@dataclass(frozen=True)
class HullConfig(_SubConfig):
    """Nodes off the body (a deviation, fit/hull_nodes.py; docs/fit.md "hull nodes"): K of the N nodes placed where
    the training masks' visual hull keeps showing the subject beyond the body (loose clothing)."""

    nodes: int | str = 0  # K (0: all N on the surface, Sec. 3.1) | "auto": decided from the masks at fit start
    # hull points farther than this (metres) from every surface node are off-body; a group of off-body cells none of
    # which comes this close to the canonical body is not worn (fit/hull_nodes.py `worn_cells`)
    min_dist: float = 0.14
    auto_fraction: float = 0.25  # "auto" says yes: this share of the N nodes goes off the body (32 of 128)
    auto_min_volume: float = 0.1  # "auto" says yes when the persistent off-body cells hold >= this x body volume
    # garment tracking on a loose garment (FitConfig.track, "auto" said yes): the nodes in all, half of them off the
    # body, the Gaussians per node scaled to keep their total (`ModelConfig.for_tracked_garment`); 0: as set
    tracked_nodes: int = 0

    def __post_init__(self) -> None:
        def need(ok: bool, msg: str) -> None:
            if not ok:
                raise ValueError(f"HullConfig: {msg}")

        need(self.nodes == AUTO or (isinstance(self.nodes, int) and not isinstance(self.nodes, bool)
                                    and self.nodes >= 0), f"nodes must be an int >= 0 or {AUTO!r}, got "
                                                          f"{self.nodes!r}")
        need(self.min_dist > 0, f"min_dist must be > 0 (metres), got {self.min_dist}")
        need(0 < self.auto_fraction < 1, f"auto_fraction must be in (0, 1), got {self.auto_fraction}")
        need(self.auto_min_volume >= 0, f"auto_min_volume must be >= 0 (a share of the body volume), got "
             f"{self.auto_min_volume}")
        need(isinstance(self.tracked_nodes, int) and not isinstance(self.tracked_nodes, bool)
             and self.tracked_nodes >= 0, f"tracked_nodes must be an int >= 0, got {self.tracked_nodes!r}")

    @property
    def on(self) -> bool:
        """Some nodes may go off the body (K > 0 or "auto")."""
        return self.nodes != 0


@dataclass(frozen=True)
class OccupancyConfig(_SubConfig):
    """Empty-space skipping (a deviation when on, model/occupancy.py; docs/fit.md): per-node occupancy grids, only
    the samples in occupied (or unseen) cells are evaluated."""

    enabled: bool = False
    res: int = 16  # cells per side of each node's occupancy grid
    threshold: float = 0.5  # density (1/metre) at or above which a cell is occupied
    decay: float = 0.95  # EMA-max decay of a cell's density at each observation
    explore: float = 0.05  # training: share of skipped samples evaluated anyway (so cells can re-open)
    warmup: int = 256  # training: grid updates (steps) during which every sample is evaluated

    def __post_init__(self) -> None:
        def need(ok: bool, msg: str) -> None:
            if not ok:
                raise ValueError(f"OccupancyConfig: {msg}")

        need(isinstance(self.enabled, bool), f"enabled must be a bool, got {self.enabled!r}")
        _need_int("OccupancyConfig", "res", self.res, 1)
        _need_int("OccupancyConfig", "warmup", self.warmup, 0)
        need(self.threshold >= 0, f"threshold must be >= 0 (density, 1/metre), got {self.threshold}")
        need(0.0 <= self.decay <= 1.0, f"decay must be in [0, 1], got {self.decay}")
        need(0.0 <= self.explore <= 1.0, f"explore must be in [0, 1], got {self.explore}")


@dataclass(frozen=True)
class PoseRefineConfig(_SubConfig):
    """Per-frame body-pose refinement (a deviation when on, model/pose_refine.py; issue 13, docs/fit.md "Pose
    refinement"): per-training-frame joint rotations / root translation optimised with the avatar."""

    # True | False | "auto": on when the capture's body fits are not ground truth (real captures, synth with
    # --fit-noise), decided at fit start; the saved config holds the decision
    enabled: bool | str = False
    lambda_pose: float = 100.0  # weight of the penalty sum over joints of |delta|^2 + |tau / 0.1 m|^2
    min_share: float = 0.04  # refine joints whose subtree carries >= this share of the skinning weight
    lr: float = 3e-4  # Adam rate of the corrections (1e-3 until 2026-11-25); the networks use FitConfig.lr
    start: int = 0  # the corrections stay frozen (lr 0) before this step: the avatar takes shape first

    def __post_init__(self) -> None:
        def need(ok: bool, msg: str) -> None:
            if not ok:
                raise ValueError(f"PoseRefineConfig: {msg}")

        _need_switch("PoseRefineConfig", self.enabled)
        need(self.lambda_pose >= 0, f"lambda_pose must be >= 0, got {self.lambda_pose}")
        need(0.0 <= self.min_share < 1.0, f"min_share must be in [0, 1), got {self.min_share}")
        need(self.lr > 0 and self.lr != float("inf"), f"lr must be > 0, got {self.lr}")
        _need_int("PoseRefineConfig", "start", self.start, 0)

    @property
    def on(self) -> bool:
        """Refinement is on; "auto" must have been decided (`resolved`) before a model is built."""
        if self.enabled == AUTO:
            raise ValueError("model.pose_refine.enabled='auto' is decided from the capture at fit start "
                             "(`PoseRefineConfig.resolved`); pass true or false to build a model directly")
        return bool(self.enabled)

    def resolved(self, fits_are_ground_truth: bool) -> "PoseRefineConfig":
        """"auto" decided: on when the body fits are not ground truth; true / false unchanged."""
        if self.enabled != AUTO:
            return self
        return replace(self, enabled=not fits_are_ground_truth)


# Flat keys of configs written before the sub-configs (schema_version 1) -> (sub-config, field). `--set` accepts
# them too, so the commands recorded in docs/ keep working.
LEGACY_KEYS: dict[str, tuple[str, str]] = {
    "hull_nodes": ("hull", "nodes"), "hull_min_dist": ("hull", "min_dist"),
    "hull_auto_fraction": ("hull", "auto_fraction"), "hull_auto_min_volume": ("hull", "auto_min_volume"),
    "occupancy": ("occupancy", "enabled"), "occ_res": ("occupancy", "res"), "occ_threshold": ("occupancy", "threshold"),
    "occ_decay": ("occupancy", "decay"), "occ_explore": ("occupancy", "explore"), "occ_warmup": ("occupancy", "warmup"),
    "pose_refine": ("pose_refine", "enabled"), "lambda_pose": ("pose_refine", "lambda_pose"),
    "pose_refine_min_share": ("pose_refine", "min_share"),
    # FitConfig's, before they moved into model.pose_refine
    "lr_pose": ("pose_refine", "lr"), "pose_refine_start": ("pose_refine", "start"),
}


def nest_legacy_keys(d: dict[str, Any]) -> dict[str, Any]:
    """A model config dict with flat legacy keys (`LEGACY_KEYS`) -> the nested form (a new dict)."""
    d = dict(d)
    flat = {k: d.pop(k) for k in list(d) if k in LEGACY_KEYS and not isinstance(d[k], dict)}
    for key, value in flat.items():
        group, name = LEGACY_KEYS[key]
        d[group] = {**(d.get(group) or {}), name: value}
    return d


LOW_PASS_BEFORE = 0.3  # GaussianConfig.low_pass of configs written before the option (3DGS's value)
SHADING_BEFORE = "none"  # GaussianConfig.shading of configs written before the option
SHADINGS = ("none", "irradiance")


@dataclass(frozen=True)
class GaussianConfig(_SubConfig):
    """Options of the structured local Gaussian fields (`ModelConfig.field = "gaussians"`, a deviation: model/
    gaussian_field.py, docs/fit.md). Used by no other backend."""

    per_node: int = 192  # K Gaussians owned by each node (fixed budget: N K Gaussians, memory known in advance)
    feature_dim: int = 16  # appearance feature of a Gaussian, decoded with the node's e_i
    decoder_width: int = 32  # hidden channels of the per-node decoder (one ReLU layer)
    # spherical-harmonic degree of the colours, at most 1; 0 (view-independent) measured better with sparse views
    # (synth tight, 4 views, 10 min: novel poses +1.00 dB, held-out views +1.46; synth small +0.12; docs/fit.md)
    sh_degree: int = 0
    init_opacity: float = 0.3
    offset_scale: float = 0.02  # metres: the decoder's offset output is multiplied by this (detail motion)
    # px^2 added to every splat's 2D covariance when rasterized (splat/project.py), in training and rendering alike;
    # 3DGS's 0.3 blurs silhouettes, 0.1 measured better (docs/fit.md "The splats' low-pass"); a saved config from
    # before the option reads 0.3, the value it was trained with (`ModelConfig.from_json`)
    low_pass: float = 0.1
    # "irradiance": a Gaussian's colour is its own (an albedo) times the shading of its world-space normal under one
    # learned order-2 spherical-harmonic irradiance of the whole avatar (fixed world lights; model/gaussian_field.py);
    # "none": its colour whatever the pose. "irradiance" measured better (synth tight's novel poses +1.2 dB at 10 min;
    # docs/fit.md "Shading under fixed lights"); a saved config from before the option reads "none"
    shading: str = "irradiance"
    # losses: (1 - lambda_ssim) L1 + lambda_ssim D-SSIM per image; lambda_mask |alpha - mask| (deviation). 3DGS's
    # lambda_ssim is 0.2; 0.1 measured better on all three synth captures, 0 better still with a skirt but not on
    # tight clothing (docs/fit.md, docs/experiments/gaussian_tiny_2026-11-27)
    lambda_ssim: float = 0.1
    lambda_mask: float = 0.1
    # pixels either side of each training crop's mask outline left out of the image loss (L1, D-SSIM, mask term), as
    # Neural Body leaves out its masks' border: an estimated mask's outline is wrong by a pixel or two. "auto": 1 where
    # the masks are not the capture's ground truth (estimated by ingest, or a real capture's) and each frame has two
    # training views or more, else 0; decided at fit start (`resolved`), the saved config holds the decision. Synth
    # realistic, 300 s: +0.06 / +0.10 dB held-out; a phone video level (docs/fit.md "The masks' outline left out")
    mask_border_px: int | str = 0
    # learning rates of the Gaussians' own parameters (3DGS's; the networks use FitConfig.lr)
    lr_means: float = 1.6e-4  # metres
    lr_scales: float = 5e-3  # log metres
    lr_quats: float = 1e-3
    lr_opacity: float = 5e-2  # logit
    lr_colors: float = 2.5e-3  # SH coefficients and appearance features
    # density control under the fixed budget (3DGS-MCMC's relocation, within each node): every `relocate_every`
    # steps the Gaussians with opacity < `min_opacity` move onto live ones of their node (0: never)
    relocate_every: int = 100
    min_opacity: float = 0.005

    def __post_init__(self) -> None:
        def need(ok: bool, msg: str) -> None:
            if not ok:
                raise ValueError(f"GaussianConfig: {msg}")

        if self.mask_border_px != AUTO:
            _need_int("GaussianConfig", "mask_border_px", self.mask_border_px, 0)
        for name in ("per_node", "feature_dim", "decoder_width"):
            v = getattr(self, name)
            need(isinstance(v, int) and not isinstance(v, bool) and v > 0, f"{name} must be a positive int, got {v!r}")
        need(self.sh_degree in (0, 1), f"sh_degree must be 0 or 1, got {self.sh_degree!r}")
        need(self.shading in SHADINGS, f"shading must be one of {', '.join(SHADINGS)}, got {self.shading!r}")
        need(isinstance(self.relocate_every, int) and self.relocate_every >= 0,
             f"relocate_every must be an int >= 0, got {self.relocate_every!r}")
        need(0 < self.init_opacity < 1, f"init_opacity must be in (0, 1), got {self.init_opacity}")
        need(0 <= self.min_opacity < self.init_opacity, f"min_opacity must be in [0, init_opacity), got "
             f"{self.min_opacity}")
        need(0 <= self.lambda_ssim <= 1, f"lambda_ssim must be in [0, 1], got {self.lambda_ssim}")
        for name in ("offset_scale", "lambda_mask", "low_pass"):
            need(getattr(self, name) >= 0, f"{name} must be >= 0, got {getattr(self, name)}")
        for name in ("lr_means", "lr_scales", "lr_quats", "lr_opacity", "lr_colors"):
            need(getattr(self, name) > 0, f"{name} must be > 0, got {getattr(self, name)}")

    @property
    def border_px(self) -> int:
        """`mask_border_px`; "auto" must have been decided (`resolved`) before a model is trained."""
        if self.mask_border_px == AUTO:
            raise ValueError("model.gaussians.mask_border_px='auto' is decided from the capture at fit start "
                             "(`GaussianConfig.resolved`); pass a number of pixels to train a model directly")
        return int(self.mask_border_px)

    def resolved(self, masks_are_ground_truth: bool, train_views: int) -> "GaussianConfig":
        """"auto" decided: 1 px where the masks are not the capture's ground truth and each frame has two training
        views or more; 0 with true masks, or from one view (there the outline is the shape's only measure)."""
        if self.mask_border_px != AUTO:
            return self
        return replace(self, mask_border_px=0 if masks_are_ground_truth or train_views < 2 else 1)


@dataclass(frozen=True)
class ColourConfig(_SubConfig):
    """A colour transform per training camera (exposure + white balance: 3 gains + 3 offsets), learned with the avatar
    and applied to each camera's renders before the loss (a deviation when on, model/colour.py; issue 51). Off in the
    paper's settings, on in the `cpu` preset (docs/fit.md deviations: `benchmarks/realistic_capture.py`)."""

    enabled: bool = False
    lambda_identity: float = 1.0  # weight of the pull towards identity: mean over cameras of |log gain|^2 + |offset|^2
    lr: float = 2e-3  # Adam rate of the gains and offsets (the networks use FitConfig.lr)

    def __post_init__(self) -> None:
        if not isinstance(self.enabled, bool):
            raise ValueError(f"ColourConfig: enabled must be true or false, got {self.enabled!r}")
        if not self.lambda_identity >= 0:
            raise ValueError(f"ColourConfig: lambda_identity must be >= 0, got {self.lambda_identity}")
        if not (self.lr > 0 and self.lr != float("inf")):
            raise ValueError(f"ColourConfig: lr must be > 0, got {self.lr}")


@dataclass(frozen=True)
class TrackRefineConfig(_SubConfig):
    """Per-training-frame rigid corrections of the tracked garment nodes, learned with the avatar (a deviation when
    on, model/track_refine.py; issue 48, docs/fit.md "Garment tracking")."""

    # True | False | "auto": on with the tracked garment's model (`ModelConfig.for_tracked_garment`, decided at fit
    # start by fit.loop); "auto" not decided reads as off. The saved config holds the decision
    enabled: bool | str = False
    lambda_size: float = 100.0  # weight of the corrections' size, per m^2 (a radian weighs `rotation_m` metres)
    lambda_smooth: float = 2000.0  # weight of their change between consecutive training frames, per m^2
    rotation_m: float = 0.05  # metres a radian of rotation weighs as in both priors
    lr: float = 1e-3  # Adam rate of the translations (metres); the networks use FitConfig.lr
    lr_rotation: float = 3e-3  # Adam rate of the rotations (radians)
    start: int = 800  # the corrections stay frozen (lr 0) before this step: the garment's appearance takes shape first

    def __post_init__(self) -> None:
        def need(ok: bool, msg: str) -> None:
            if not ok:
                raise ValueError(f"TrackRefineConfig: {msg}")

        _need_switch("TrackRefineConfig", self.enabled)
        for name in ("lambda_size", "lambda_smooth", "rotation_m"):
            need(getattr(self, name) >= 0, f"{name} must be >= 0, got {getattr(self, name)}")
        for name in ("lr", "lr_rotation"):
            v = getattr(self, name)
            need(v > 0 and v != float("inf"), f"{name} must be > 0, got {v}")
        _need_int("TrackRefineConfig", "start", self.start, 0)

    @property
    def on(self) -> bool:
        """The corrections are learned: `enabled` is true ("auto" undecided is off)."""
        return self.enabled is True


_SUB_CONFIGS = {"hull": HullConfig, "occupancy": OccupancyConfig, "pose_refine": PoseRefineConfig,
                "gaussians": GaussianConfig, "colour": ColourConfig, "track_refine": TrackRefineConfig}


@dataclass(frozen=True)
class ModelConfig:
    """Hyperparameters of `SlrfAvatar`. Immutable; validated on construction; JSON round-trips. The defaults are the
    paper's (the `paper` preset); the other presets are in avatarctl/fit/presets.py (`PRESETS`)."""

    # representation (Eq. 1-6)
    num_nodes: int = 128  # N, nodes by farthest point sampling on the canonical surface
    hull: HullConfig = HullConfig()  # K of the N nodes off the body (deviation when on, fit/hull_nodes.py)
    sigma: float = 0.05  # Eq. 6 Gaussian width, metres
    eps: float = 0.001  # Eq. 6 truncation; support radius sigma*sqrt(-2 ln eps) = 0.186 m
    embed_dim: int = 32  # dim e_i, dynamic detail embedding
    latent_dim: int = 8  # dim z_i, cVAE latent
    # positional encodings gamma(x) = (x, sin 2^k x, cos 2^k x), k < m (supplement)
    pe_coords: int = 6
    pe_views: int = 4
    pe_time: int = 12
    # networks (our choice: the paper's architecture figure is unavailable)
    node_width: int = 128  # F_i hidden channels
    node_depth: int = 3  # F_i hidden ReLU layers
    feature_dim: int = 128  # F_i output feature f (Eq. 5)
    head_width: int = 128  # G and H hidden channels (Eq. 7)
    cvae_width: int | str = 128  # per-node encoder / decoder hidden channels | "auto": from the training views
    # local-field backend (deviation when "gaussians", see model/gaussian_field.py and docs/fit.md)
    field: str = "mlp"  # "mlp": the paper's F_i MLPs | "gaussians": per-node 3D Gaussians, see `gaussians`
    gaussians: GaussianConfig = GaussianConfig()  # options of field "gaussians" (model/gaussian_field.py)
    # rendering
    samples_per_ray: int = 64  # uniform samples between the ray's entry/exit of the node spheres
    occupancy: OccupancyConfig = OccupancyConfig()  # empty-space skipping (deviation when on, model/occupancy.py)
    # z of novel poses (deviation when "train_mean", see model/cvae.py): "zero" (paper Sec. 4.1) | "train_mean": the
    # mean over the training frames of the posterior means mu_i, per node (the decoder is trained on z ~ N(mu, sigma)
    # and never sees z = 0; issue 18, docs/experiments/garment_latent_2026-11-26)
    novel_latent: str = "zero"
    pose_refine: PoseRefineConfig = PoseRefineConfig()  # per-frame body-pose refinement (deviation when on)
    # garment tracks (a deviation, fit `track`; `SlrfAvatar._tracked`): in each training step this share of the batch's
    # training frames places the tracked nodes the paper's way (skeleton + Delta n, Eq. 1-3) instead of by the
    # tracks, so the garment is also learned where the model's own Delta n puts it, as on novel poses
    track_free: float = 0.3
    # the tracked garment nodes' per-frame corrections (a deviation when on, model/track_refine.py)
    track_refine: TrackRefineConfig = TrackRefineConfig()
    colour: ColourConfig = ColourConfig()  # a colour transform per training camera (deviation when on, model/colour.py)
    # pose condition (Eq. 8)
    pose_attention_hops: int = 2
    # ablations
    use_delta_n: bool = True  # False: Delta n_i = 0 ("no-delta-n")
    use_embedding: bool = True  # False: e_i = 0 ("no-embedding")
    latent: str = "cvae"  # "cvae" | "deterministic" | "per_frame"
    variant: str = "slrf"  # "slrf" | "lbs_baseline"
    sparse: bool = True  # supplement Sec. C.2 packed evaluation; False = dense reference path
    pack_block: int = 128  # rows per packed block (0 = the supplement's single N x max S_i tensor)
    # losses (Eq. 11)
    lambda_rec: float = 1.0
    lambda_trans: float = 0.02
    lambda_ebd: float = 0.1
    lambda_kl: float = 1e-5
    rec_reduction: str = "sum"  # Eq. 12 as written (sum over rays), see model/losses.py; "mean" = plain MSE
    rec_reference_rays: int = 2048  # L_rec is scaled by this / rays-in-batch (= Eq. 12 at the paper's 2048)

    def __post_init__(self) -> None:
        def need(ok: bool, msg: str) -> None:
            if not ok:
                raise ValueError(f"ModelConfig: {msg}")

        for name, cls in _SUB_CONFIGS.items():  # JSON: a dict of the sub-config's fields
            if isinstance(getattr(self, name), dict):
                object.__setattr__(self, name, cls.from_json(getattr(self, name)))
            need(isinstance(getattr(self, name), cls), f"{name} must be a {cls.__name__}")
        need(self.field in FIELDS, f"field must be one of {FIELDS}, got {self.field!r}")
        need(self.field != "gaussians" or self.variant == "slrf", "field 'gaussians' needs the slrf variant (the "
             "pose-only baseline is the ray-marched canonical MLP)")

        for name in ("num_nodes", "embed_dim", "latent_dim", "node_width", "node_depth", "feature_dim",
                     "head_width", "samples_per_ray"):
            v = getattr(self, name)
            need(isinstance(v, int) and not isinstance(v, bool) and v > 0, f"{name} must be a positive int, got {v!r}")
        w = self.cvae_width
        need(w == AUTO or (isinstance(w, int) and not isinstance(w, bool) and w > 0),
             f"cvae_width must be a positive int or {AUTO!r}, got {w!r}")
        for name in ("pe_coords", "pe_views", "pe_time", "pose_attention_hops"):
            v = getattr(self, name)
            need(isinstance(v, int) and not isinstance(v, bool) and v >= 0, f"{name} must be an int >= 0, got {v!r}")
        need(isinstance(self.pack_block, int) and self.pack_block >= 0, f"pack_block must be an int >= 0, got "
             f"{self.pack_block!r}")
        hull = self.hull
        need(hull.nodes == AUTO or hull.nodes < self.num_nodes,
             f"hull.nodes must be an int in [0, num_nodes={self.num_nodes}) or {AUTO!r} (decide from the "
             f"masks), got {hull.nodes!r}")
        need(hull.nodes != AUTO or self.hull_auto_nodes < self.num_nodes,
             f"hull.nodes='auto' would place {self.hull_auto_nodes} of num_nodes={self.num_nodes} nodes off the "
             f"body; use more nodes or a smaller hull.auto_fraction")
        need(hull.nodes in (0, AUTO) or self.variant == "slrf", "hull.nodes needs the slrf variant (the pose-only "
             "baseline has no nodes)")
        need(self.samples_per_ray >= 2, f"samples_per_ray must be >= 2, got {self.samples_per_ray}")
        need(self.head_width >= 2, f"head_width must be >= 2, got {self.head_width}")
        need(self.sigma > 0, f"sigma must be > 0 (metres), got {self.sigma}")
        need(0 < self.eps < 1, f"eps must be in (0, 1), got {self.eps}")
        need(self.latent in LATENTS, f"latent must be one of {LATENTS}, got {self.latent!r}")
        need(0.0 <= self.track_free < 1.0, f"track_free must be in [0, 1), got {self.track_free!r}")
        need(self.novel_latent in NOVEL_LATENTS, f"novel_latent must be one of {NOVEL_LATENTS}, got "
             f"{self.novel_latent!r}")
        need(self.variant in VARIANTS, f"variant must be one of {VARIANTS}, got {self.variant!r}")
        for name in ("use_delta_n", "use_embedding", "sparse"):
            need(isinstance(getattr(self, name), bool), f"{name} must be a bool, got {getattr(self, name)!r}")
        for name in ("lambda_rec", "lambda_trans", "lambda_ebd", "lambda_kl"):
            need(getattr(self, name) >= 0, f"{name} must be >= 0, got {getattr(self, name)}")
        need(self.rec_reduction in REC_REDUCTIONS,
             f"rec_reduction must be one of {REC_REDUCTIONS}, got {self.rec_reduction!r}")
        need(isinstance(self.rec_reference_rays, int) and self.rec_reference_rays > 0,
             f"rec_reference_rays must be a positive int, got {self.rec_reference_rays!r}")

    @property
    def cvae_channels(self) -> int:
        """The cVAE's hidden width; "auto" must have been decided (`with_cvae_width_for`) before a model is built."""
        if self.cvae_width == AUTO:
            raise ValueError("model.cvae_width='auto' is decided from the capture's training views at fit start "
                             "(`ModelConfig.with_cvae_width_for`); pass a number to build a model directly")
        return self.cvae_width

    def with_cvae_width_for(self, train_views: int) -> "ModelConfig":
        """`cvae_width = "auto"` decided from the number of training views of each frame: `CVAE_AUTO_WIDTHS[0]` (32)
        with one (a monocular capture, a phone video), `CVAE_AUTO_WIDTHS[1]` (the paper's 128) with two or more; a
        number unchanged."""
        if self.cvae_width != AUTO:
            return self
        return self.with_(cvae_width=CVAE_AUTO_WIDTHS[1] if train_views >= 2 else CVAE_AUTO_WIDTHS[0])

    def for_tracked_garment(self) -> "ModelConfig":
        """The model of a fit that tracks a loose garment (`hull.tracked_nodes` > 0; fit.loop decides when): N =
        `hull.tracked_nodes` nodes, half of them off the body (`hull.auto_fraction` 0.5: many small garment patches,
        each moved rigidly by the tracks), `gaussians.per_node` scaled so that the Gaussians' total stays (N x K), and
        `track_refine.enabled = "auto"` decided on. Unchanged when `hull.tracked_nodes` is 0 or N already."""
        n = self.hull.tracked_nodes
        if not n or n == self.num_nodes:
            return self
        per_node = max(1, round(self.num_nodes * self.gaussians.per_node / n))
        refine = {"enabled": True} if self.track_refine.enabled == AUTO else {}
        return self.with_(num_nodes=n, hull={"auto_fraction": 0.5}, gaussians={"per_node": per_node},
                          track_refine=refine)

    @property
    def hull_auto_nodes(self) -> int:
        """K when `hull.nodes = "auto"` decides for hull nodes: round(hull.auto_fraction N), at least 1."""
        return max(1, round(self.hull.auto_fraction * self.num_nodes))

    @property
    def support_radius(self) -> float:
        """Distance (metres) beyond which the Eq. 6 blending weight is exactly zero: sigma*sqrt(-2 ln eps)."""
        import math

        return self.sigma * math.sqrt(-2.0 * math.log(self.eps))

    @property
    def ray_marched(self) -> bool:
        """The field is ray-marched (mlp), not rasterized (gaussians): the options of ray marching (samples,
        occupancy grids, packing) apply."""
        return self.field != "gaussians"

    @property
    def uses_occupancy(self) -> bool:
        return self.occupancy.enabled and self.ray_marched

    def to_json(self) -> dict[str, Any]:
        return {"schema_version": SCHEMA_VERSION, **asdict(self)}

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> "ModelConfig":
        """Inverse of `to_json`. Unknown keys are an error (a typo never silently falls back to a default). Reads
        schema_version 1 too: its flat keys are nested (`LEGACY_KEYS`), its removed switches dropped
        (`REMOVED_KEYS`)."""
        d = dict(d)
        version = d.pop("schema_version", SCHEMA_VERSION)
        if version not in (1, SCHEMA_VERSION):
            raise ValueError(f"ModelConfig: schema_version {version} is not supported (expected {SCHEMA_VERSION})")
        if d.get("field") == "grid":
            raise ValueError("ModelConfig: field 'grid' (per-node feature grids) was removed in issue 28; this avatar "
                             "needs avatarctl before that change (git commit e4ec5be), or a new fit")
        if version == 1:
            _check_removed("ModelConfig", d)
            d = nest_legacy_keys(d)
        pr = d.get("pose_refine")
        if isinstance(pr, dict) and "lambda_accel" in pr:  # the smoothness term, removed 2026-11-29 (docs/fit.md
            # "Tried and removed"): it only shaped training, an avatar fitted with it renders the same
            d["pose_refine"] = {k: v for k, v in pr.items() if k != "lambda_accel"}
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"ModelConfig: unknown keys {unknown}; known keys are {sorted(known)}")
        if "rec_reduction" not in d:  # configs written before the key existed were trained with the mean
            d["rec_reduction"] = "mean"
        if d.get("field") == "gaussians":  # options an avatar saved before them was trained without
            before = {"low_pass": LOW_PASS_BEFORE, "shading": SHADING_BEFORE}
            d["gaussians"] = {**before, **(d.get("gaussians") or {})}
        return cls(**d)

    def with_(self, **changes: Any) -> "ModelConfig":
        """A validated copy with some fields changed (e.g. `cfg.with_(sparse=False)`). A sub-config may be given as
        a dict of the fields to change in it: `cfg.with_(occupancy={"enabled": False})`."""
        for name, value in list(changes.items()):
            if name in _SUB_CONFIGS and isinstance(value, dict):
                changes[name] = replace(getattr(self, name), **value)
        return replace(self, **changes)
