"""`ModelConfig`: every hyperparameter of the structured local radiance fields (SLRF) model.

Defaults are the supplement's table (N=128, sigma=0.05, eps=0.001, dim e=32, dim z=8, 64 uniform samples per
ray, lambda_rec/trans/ebd/KL = 1 / 0.02 / 0.1 / 1e-5, positional encodings m = 6 / 4 / 12). The network widths are
our choice because the paper's architecture figure (supp. Fig. A) is not available:

- local fields F_i: `node_depth` fully connected ReLU layers of `node_width` channels, then a linear layer to a
  `feature_dim` feature (paper preset 3 x 128 -> 128);
- heads: density H(f) = Linear(f, head_width) -> ReLU -> Linear(1) -> softplus; colour
  G(f, v) = Linear([f, gamma(v)], head_width) -> ReLU -> Linear(head_width // 2) -> ReLU -> Linear(3) -> sigmoid;
- per-node cVAE encoder and decoder: two ReLU layers of `cvae_width` channels each.

Presets: "paper" = the defaults; "cpu" = the same model with narrower networks (node 2 x 32 -> 32, heads 64,
cVAE 32) so a training step with a few hundred rays takes well under a second on 2 CPU cores, and with empty-space
skipping on (`occupancy`, model/occupancy.py: same images, ~20 % more steps per second, measured in docs/fit.md) and
hull nodes decided from the masks (`hull_nodes = "auto"`, fit/hull_nodes.py: +0.4 dB on the skirt capture, the
paper's placement on tight clothing; docs/experiments/hull_auto_2026-11-25) and z of novel poses = the mean posterior
mean of the training frames (`novel_latent = "train_mean"`, model/cvae.py: +0.08 / +0.15 dB box and +0.3 / +0.4 dB
body on synth small's novel poses, training frames unchanged; docs/experiments/garment_latent_2026-11-26).

Choices beyond the paper text (documented, switchable):
- `local_coords_in_sigma`: local coordinates p_i (Eq. 4) are divided by sigma before the positional encoding, so
  the node's support (radius sigma*sqrt(-2 ln eps) = 3.7 sigma) spans ~3.7 units and the highest frequency
  2^(m-1) = 32 resolves ~1 cm; in metres (False) the same encoding would resolve only ~20 cm inside a node.
- `pack_block` (speed, not maths): the supplement packs the valid pairs into one N x max_i(S_i) tensor, which is
  mostly padding when S_i varies a lot between nodes (39-59% fill measured on anny). With `pack_block` = b > 0 each
  node's pairs fill ceil(S_i / b) blocks of b rows and every block carries its node's weights (a gather), so
  padding is < b rows per node. Same outputs and gradients; `pack_block = 0` is the supplement's layout.
- `pose_attention_hops`: the SCANimate-style attention map W (Eq. 8) lets joint k attend to every joint within
  this many hops in the kinematic tree (see `deformer.pose_attention_map`).
- `pe_anneal_steps` (off in every preset): coarse-to-fine gamma(p) of the MLP fields (model/encoding.py), measured
  no better than the plain encoding (docs/fit.md).
- `field = "gaussians"`: structured local Gaussian fields (model/gaussian_field.py), K 3D Gaussians per node,
  rasterized instead of ray-marched; its options live in `GaussianConfig` (`model.gaussians.*`), docs/fit.md.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields, replace
from typing import Any

SCHEMA_VERSION = 1
LATENTS = ("cvae", "deterministic", "per_frame")
VARIANTS = ("slrf", "lbs_baseline")
# local fields F_i: the paper's per-node MLPs | per-node 3D Gaussians rasterized instead of ray-marched
# (model/gaussian_field.py, options in `GaussianConfig`). The per-node feature grids ("grid") were removed in issue 28
# (beaten by the Gaussians at equal wall time; figures in docs/fit.md, "Tried and removed").
FIELDS = ("mlp", "gaussians")
REMOVED_MODEL_KEYS = ("grid_levels", "grid_channels")  # in configs written before issue 28: dropped on reading
REC_REDUCTIONS = ("sum", "mean")  # Eq. 12 as written (sum over rays) | plain MSE, see model/losses.py
NOVEL_LATENTS = ("zero", "train_mean")  # z of novel poses: the paper's 0 | the mean of mu over the training frames
HULL_AUTO = "auto"  # `hull_nodes`: decide from the training masks at fit start (fit/hull_nodes.py)


@dataclass(frozen=True)
class GaussianConfig:
    """Options of the structured local Gaussian fields (`ModelConfig.field = "gaussians"`, a deviation: model/
    gaussian_field.py, docs/fit.md). Used by no other backend."""

    per_node: int = 192  # K Gaussians owned by each node (fixed budget: N K Gaussians, memory known in advance)
    feature_dim: int = 16  # appearance feature of a Gaussian, decoded with the node's e_i
    decoder_width: int = 32  # hidden channels of the per-node decoder (one ReLU layer)
    sh_degree: int = 1  # spherical-harmonic degree of the colours (0: view-independent; at most 1)
    init_opacity: float = 0.3
    offset_scale: float = 0.02  # metres: the decoder's offset output is multiplied by this (detail motion)
    # losses (3DGS): (1 - lambda_ssim) L1 + lambda_ssim D-SSIM per image; lambda_mask |alpha - mask| (deviation)
    lambda_ssim: float = 0.2
    lambda_mask: float = 0.1
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

        for name in ("per_node", "feature_dim", "decoder_width"):
            v = getattr(self, name)
            need(isinstance(v, int) and not isinstance(v, bool) and v > 0, f"{name} must be a positive int, got {v!r}")
        need(self.sh_degree in (0, 1), f"sh_degree must be 0 or 1, got {self.sh_degree!r}")
        need(isinstance(self.relocate_every, int) and self.relocate_every >= 0,
             f"relocate_every must be an int >= 0, got {self.relocate_every!r}")
        need(0 < self.init_opacity < 1, f"init_opacity must be in (0, 1), got {self.init_opacity}")
        need(0 <= self.min_opacity < self.init_opacity, f"min_opacity must be in [0, init_opacity), got "
             f"{self.min_opacity}")
        need(0 <= self.lambda_ssim <= 1, f"lambda_ssim must be in [0, 1], got {self.lambda_ssim}")
        for name in ("offset_scale", "lambda_mask"):
            need(getattr(self, name) >= 0, f"{name} must be >= 0, got {getattr(self, name)}")
        for name in ("lr_means", "lr_scales", "lr_quats", "lr_opacity", "lr_colors"):
            need(getattr(self, name) > 0, f"{name} must be > 0, got {getattr(self, name)}")

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> "GaussianConfig":
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"GaussianConfig: unknown keys {unknown}; known keys are {sorted(known)}")
        return cls(**d)


@dataclass(frozen=True)
class ModelConfig:
    """Hyperparameters of `SlrfAvatar`. Immutable; validated on construction; JSON round-trips."""

    # representation (Eq. 1-6)
    num_nodes: int = 128  # N, nodes by farthest point sampling on the canonical surface
    # K of the N placed off the body from the masks' visual hull (deviation, fit/hull_nodes.py); "auto": decided
    # from the masks at fit start (hull_auto_fraction N nodes or none)
    hull_nodes: int | str = 0
    hull_min_dist: float = 0.14  # hull points farther than this (metres) from every surface node are off-body
    hull_auto_fraction: float = 0.25  # "auto" says yes: this share of the N nodes goes off the body (32 of 128)
    hull_auto_min_volume: float = 0.1  # "auto" says yes when the persistent off-body cells hold >= this x body volume
    sigma: float = 0.05  # Eq. 6 Gaussian width, metres
    eps: float = 0.001  # Eq. 6 truncation; support radius sigma*sqrt(-2 ln eps) = 0.186 m
    embed_dim: int = 32  # dim e_i, dynamic detail embedding
    latent_dim: int = 8  # dim z_i, cVAE latent
    # positional encodings gamma(x) = (x, sin 2^k x, cos 2^k x), k < m (supplement)
    pe_coords: int = 6
    pe_views: int = 4
    pe_time: int = 12
    local_coords_in_sigma: bool = True  # p_i / sigma before gamma (our choice, see module docstring)
    # coarse-to-fine gamma(p) (deviation when > 0, see model/encoding.py `band_weights`): the coordinate encoding of
    # the MLP fields opens from `pe_anneal_start` frequency bands to all `pe_coords` over the first `pe_anneal_steps`
    # training steps (0: all bands from the start, the paper)
    pe_anneal_steps: int = 0
    pe_anneal_start: float = 3.0
    # networks (our choice: the paper's architecture figure is unavailable)
    node_width: int = 128  # F_i hidden channels
    node_depth: int = 3  # F_i hidden ReLU layers
    feature_dim: int = 128  # F_i output feature f (Eq. 5)
    head_width: int = 128  # G and H hidden channels (Eq. 7)
    cvae_width: int = 128  # per-node encoder / decoder hidden channels
    # local-field backend (deviation when "gaussians", see model/gaussian_field.py and docs/fit.md)
    field: str = "mlp"  # "mlp": the paper's F_i MLPs | "gaussians": per-node 3D Gaussians, see `gaussians`
    gaussians: GaussianConfig = GaussianConfig()  # options of field "gaussians" (model/gaussian_field.py)
    # density head H (deviation when not 1 / 0, see model/field.py RadianceHeads)
    density_scale: float = 1.0  # sigma = density_scale * softplus(x + density_shift), 1/metre
    density_shift: float = 0.0
    # rendering
    samples_per_ray: int = 64  # uniform samples between the ray's entry/exit of the node spheres
    # empty-space skipping (deviation when on, see model/occupancy.py and docs/fit.md)
    occupancy: bool = False  # evaluate only samples in occupied cells of the per-node occupancy grids
    occ_res: int = 16  # cells per side of each node's occupancy grid
    occ_threshold: float = 0.5  # density (1/metre) at or above which a cell is occupied
    occ_decay: float = 0.95  # EMA-max decay of a cell's density at each observation
    occ_explore: float = 0.05  # training: share of skipped samples evaluated anyway (so cells can re-open)
    occ_warmup: int = 256  # training: grid updates (steps) during which every sample is evaluated
    occ_stop_eps: float = 0.0  # skip samples whose transmittance estimated from the cached densities is below this
    # cVAE posterior (deviation when != 0): initial log-variance of q(z | t, theta) (issue 18, hypothesis 1)
    posterior_logvar_init: float = 0.0  # 0: the encoder's plain init (sigma ~ 1); e.g. -6 starts sigma ~ 0.05
    # z of novel poses (deviation when "train_mean", see model/cvae.py): "zero" (paper Sec. 4.1) | "train_mean": the
    # mean over the training frames of the posterior means mu_i, per node (the decoder is trained on z ~ N(mu, sigma)
    # and never sees z = 0; issue 18, docs/experiments/garment_latent_2026-11-26)
    novel_latent: str = "zero"
    # per-frame body-pose refinement (deviation when on, see model/pose_refine.py; issue 13)
    pose_refine: bool = False  # optimise per-training-frame joint rotations / root translation with the avatar
    lambda_pose: float = 100.0  # weight of the refinement penalty (sum over joints of |delta|^2 + |tau / 0.1 m|^2)
    pose_refine_min_share: float = 0.04  # refine joints whose subtree carries >= this share of the skinning weight
    lambda_pose_accel: float = 2e-3  # temporal smoothness of the refined poses, per (m/s^2)^2 (0: off; pose_refine.py)
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

        need(self.field in FIELDS, f"field must be one of {FIELDS}, got {self.field!r}")
        if isinstance(self.gaussians, dict):  # JSON
            object.__setattr__(self, "gaussians", GaussianConfig.from_json(self.gaussians))
        need(isinstance(self.gaussians, GaussianConfig), "gaussians must be a GaussianConfig")
        need(self.field != "gaussians" or self.variant == "slrf", "field 'gaussians' needs the slrf variant (the "
             "pose-only baseline is the ray-marched canonical MLP)")

        for name in ("num_nodes", "embed_dim", "latent_dim", "node_width", "node_depth", "feature_dim",
                     "head_width", "cvae_width", "samples_per_ray", "occ_res"):
            v = getattr(self, name)
            need(isinstance(v, int) and not isinstance(v, bool) and v > 0, f"{name} must be a positive int, got {v!r}")
        for name in ("pe_coords", "pe_views", "pe_time", "pose_attention_hops", "occ_warmup", "pe_anneal_steps"):
            v = getattr(self, name)
            need(isinstance(v, int) and not isinstance(v, bool) and v >= 0, f"{name} must be an int >= 0, got {v!r}")
        need(isinstance(self.pack_block, int) and self.pack_block >= 0, f"pack_block must be an int >= 0, got "
             f"{self.pack_block!r}")
        need(self.hull_nodes == HULL_AUTO or (isinstance(self.hull_nodes, int) and not isinstance(self.hull_nodes, bool)
                                              and 0 <= self.hull_nodes < self.num_nodes),
             f"hull_nodes must be an int in [0, num_nodes={self.num_nodes}) or {HULL_AUTO!r} (decide from the "
             f"masks), got {self.hull_nodes!r}")
        need(self.hull_min_dist > 0, f"hull_min_dist must be > 0 (metres), got {self.hull_min_dist}")
        need(0 < self.hull_auto_fraction < 1, f"hull_auto_fraction must be in (0, 1), got {self.hull_auto_fraction}")
        need(self.hull_nodes != HULL_AUTO or self.hull_auto_nodes < self.num_nodes,
             f"hull_nodes='auto' would place {self.hull_auto_nodes} of num_nodes={self.num_nodes} nodes off the "
             f"body; use more nodes or a smaller hull_auto_fraction")
        need(self.hull_auto_min_volume >= 0, f"hull_auto_min_volume must be >= 0 (a share of the body volume), got "
             f"{self.hull_auto_min_volume}")
        need(self.hull_nodes in (0, HULL_AUTO) or self.variant == "slrf", "hull_nodes needs the slrf variant (the pose-only "
             "baseline has no nodes)")
        need(0.0 <= self.pe_anneal_start <= self.pe_coords, f"pe_anneal_start must be in [0, pe_coords="
             f"{self.pe_coords}] (frequency bands open at the first step), got {self.pe_anneal_start}")
        need(self.samples_per_ray >= 2, f"samples_per_ray must be >= 2, got {self.samples_per_ray}")
        need(self.head_width >= 2, f"head_width must be >= 2, got {self.head_width}")
        need(self.sigma > 0, f"sigma must be > 0 (metres), got {self.sigma}")
        need(0 < self.eps < 1, f"eps must be in (0, 1), got {self.eps}")
        need(self.latent in LATENTS, f"latent must be one of {LATENTS}, got {self.latent!r}")
        need(self.novel_latent in NOVEL_LATENTS, f"novel_latent must be one of {NOVEL_LATENTS}, got "
             f"{self.novel_latent!r}")
        need(self.variant in VARIANTS, f"variant must be one of {VARIANTS}, got {self.variant!r}")
        need(self.density_scale > 0, f"density_scale must be > 0, got {self.density_scale}")
        need(0.0 <= self.pose_refine_min_share < 1.0,
             f"pose_refine_min_share must be in [0, 1), got {self.pose_refine_min_share}")
        need(self.occ_threshold >= 0, f"occ_threshold must be >= 0 (density, 1/metre), got {self.occ_threshold}")
        need(0.0 <= self.occ_decay <= 1.0, f"occ_decay must be in [0, 1], got {self.occ_decay}")
        need(0.0 <= self.occ_explore <= 1.0, f"occ_explore must be in [0, 1], got {self.occ_explore}")
        need(0.0 <= self.occ_stop_eps < 1.0, f"occ_stop_eps must be in [0, 1), got {self.occ_stop_eps}")
        for name in ("use_delta_n", "use_embedding", "sparse", "local_coords_in_sigma", "occupancy", "pose_refine"):
            need(isinstance(getattr(self, name), bool), f"{name} must be a bool, got {getattr(self, name)!r}")
        for name in ("lambda_rec", "lambda_trans", "lambda_ebd", "lambda_kl", "lambda_pose", "lambda_pose_accel"):
            need(getattr(self, name) >= 0, f"{name} must be >= 0, got {getattr(self, name)}")
        need(self.rec_reduction in REC_REDUCTIONS,
             f"rec_reduction must be one of {REC_REDUCTIONS}, got {self.rec_reduction!r}")
        need(isinstance(self.rec_reference_rays, int) and self.rec_reference_rays > 0,
             f"rec_reference_rays must be a positive int, got {self.rec_reference_rays!r}")

    @property
    def hull_auto_nodes(self) -> int:
        """K when `hull_nodes = "auto"` decides for hull nodes: round(hull_auto_fraction N), at least 1."""
        return max(1, round(self.hull_auto_fraction * self.num_nodes))

    @property
    def support_radius(self) -> float:
        """Distance (metres) beyond which the Eq. 6 blending weight is exactly zero: sigma*sqrt(-2 ln eps)."""
        import math

        return self.sigma * math.sqrt(-2.0 * math.log(self.eps))

    @property
    def ray_marched(self) -> bool:
        """The field is ray-marched (mlp, grid), not rasterized (gaussians): the options of ray marching (samples,
        occupancy grids, packing) apply."""
        return self.field != "gaussians"

    @property
    def uses_occupancy(self) -> bool:
        return self.occupancy and self.ray_marched

    def to_json(self) -> dict[str, Any]:
        return {"schema_version": SCHEMA_VERSION, **asdict(self)}

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> "ModelConfig":
        """Inverse of `to_json`. Unknown keys are an error (a typo never silently falls back to a default)."""
        d = dict(d)
        version = d.pop("schema_version", SCHEMA_VERSION)
        if version != SCHEMA_VERSION:
            raise ValueError(f"ModelConfig: schema_version {version} is not supported (expected {SCHEMA_VERSION})")
        if d.get("field") == "grid":
            raise ValueError("ModelConfig: field 'grid' (per-node feature grids) was removed in issue 28; this avatar "
                             "needs avatarctl before that change (git commit e4ec5be), or a new fit")
        for key in REMOVED_MODEL_KEYS:
            d.pop(key, None)
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"ModelConfig: unknown keys {unknown}; known keys are {sorted(known)}")
        if "rec_reduction" not in d:  # configs written before the key existed were trained with the mean
            d["rec_reduction"] = "mean"
        return cls(**d)

    @classmethod
    def preset(cls, name: str) -> "ModelConfig":
        """"paper": the defaults. "cpu": narrower networks, empty-space skipping, hull nodes where the masks show
        loose clothing (`hull_nodes = "auto"`, fit/hull_nodes.py) and the training frames' mean latent for novel poses
        (`novel_latent = "train_mean"`, model/cvae.py; see module docstring). The Gaussian local fields
        (`--set model.field=gaussians`) are not its default: better at equal wall time on synth small, but the demo's
        novel-view PSNR and its exported mesh were lower with them (docs/fit.md)."""
        if name == "paper":
            return cls()
        if name == "cpu":
            return cls(node_width=32, node_depth=2, feature_dim=32, head_width=64, cvae_width=32, occupancy=True,
                       hull_nodes=HULL_AUTO, novel_latent="train_mean")
        raise ValueError(f"ModelConfig: unknown preset {name!r}; use 'paper' or 'cpu'")

    def with_(self, **changes: Any) -> "ModelConfig":
        """A validated copy with some fields changed (e.g. `cfg.with_(sparse=False)`)."""
        return replace(self, **changes)
