"""What an evaluation saves: `EvalMetrics` (`eval/<name>/metrics.json`) and the per-image scores (`per_frame.csv`).

`EvalMetrics.to_json` writes exactly the keys of metrics.json (schema_version 1); `from_json` reads them back and
fails on a missing key (a typo never turns into a default).
"""

from __future__ import annotations

import csv
import io
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

SCHEMA_VERSION = 1
PSNR_CAP = 100.0  # dB; an exact reconstruction (MSE 0, PSNR inf) is reported as this so JSON stays valid


@dataclass(frozen=True)
class ImageScore:
    frame: int
    view: str
    psnr: float  # dB over the protocol's region
    ssim: float  # on the protocol's crop
    mse: float
    pixels: int  # PSNR pixels
    latent: str
    seconds: float  # render time
    region_mse: dict[str, float] | None = None  # {"garment", "body", "garment_flat", "body_flat"} with gt geometry
    region_pixels: dict[str, int] | None = None
    matched: "MatchedScore | None" = None  # the colour-matched score (NeRF-W's protocol), None: a half was empty
    refined: "RefinedScore | None" = None  # the same image after its frame's pose refinement (`--refine-pose`)
    mse_rgb: tuple[float, float, float] | None = None  # per channel over the same pixels (`mse` is their mean)


@dataclass(frozen=True)
class RefinedScore:
    """One image scored after its frame's body pose was refined against the frame's images, the avatar frozen
    (`fit.frame_pose`; the monocular papers' test-time protocol): the same pixels as the plain score."""

    psnr: float
    ssim: float
    mse: float
    shift_cm: float  # the frame's root translation correction, cm
    max_angle_deg: float  # the frame's largest joint rotation correction, degrees


@dataclass(frozen=True)
class MatchedScore:
    """One image scored NeRF-W's way (`evaluate.colour`): the camera's colour transform estimated on the LEFT half of
    the protocol's region, the render through it scored on the RIGHT half."""

    mse: float  # right half, the render through the estimated transform
    plain_mse: float  # right half, the render as it is (the same pixels: the plain figure to compare with)
    gain: list[float]  # [3] the estimated transform
    offset: list[float]  # [3]


@dataclass(frozen=True)
class ColourMatched:
    """metrics.json "colour_matched": the split scored with each image's camera colour estimated from its left half
    and scored on its right half (NeRF-W's protocol for cameras the avatar never saw; issue 51), beside the plain
    render's score on the same right halves. Only over the protocol's region (`EvalMetrics.region` does not apply)."""

    psnr: float  # mean over images of the per-image right-half PSNR after the transform, dB
    plain_psnr: float  # mean over the same images of the plain right-half PSNR, dB
    images: int  # images with both halves non-empty
    gain: dict[str, list[float]]  # per view: the mean estimated gain [3] (how the camera disagrees with the avatar)
    offset: dict[str, list[float]]  # per view: the mean estimated offset [3]
    protocol: str


def colour_matched(scores: list[ImageScore], protocol: str) -> ColourMatched | None:
    """The split's `ColourMatched` from the images' `matched` scores (None when no image has one)."""
    import numpy as np

    from avatarctl.evaluate.metrics import psnr_from_mse

    got = [s for s in scores if s.matched is not None]
    if not got:
        return None
    views = sorted({s.view for s in got})
    return ColourMatched(
        psnr=float(np.mean([min(PSNR_CAP, psnr_from_mse(s.matched.mse)) for s in got])),
        plain_psnr=float(np.mean([min(PSNR_CAP, psnr_from_mse(s.matched.plain_mse)) for s in got])),
        images=len(got),
        gain={v: np.mean([s.matched.gain for s in got if s.view == v], 0).round(4).tolist() for v in views},
        offset={v: np.mean([s.matched.offset for s in got if s.view == v], 0).round(4).tolist() for v in views},
        protocol=protocol)


@dataclass(frozen=True)
class RefinedPose:
    """metrics.json "refined_pose": the split scored after each frame's body pose was refined against that frame's
    scored images with the avatar frozen (InstantAvatar's / GART's test-time protocol for held-out poses; issue 51),
    beside the plain figure, never in place of it. Over the protocol's region (`EvalMetrics.region` does not apply)."""

    psnr: float  # mean over images of the per-image PSNR after refinement, dB
    ssim: float
    plain_psnr: float  # the plain figure over the same images, dB
    images: int
    steps: int  # Adam steps per frame
    shift_cm: float  # mean over frames of the root translation correction, cm
    max_angle_deg: float  # the largest joint rotation correction of any frame, degrees
    seconds: float  # refinement time, all frames
    protocol: str
    target: str  # what each pose was refined against: images (colours and masks) | masks (alone)


def refined_pose(scores: list[ImageScore], steps: int, seconds: float, protocol: str,
                 target: str) -> RefinedPose | None:
    """The split's `RefinedPose` from the images' `refined` scores (None when no image has one)."""
    import numpy as np

    got = [s for s in scores if s.refined is not None]
    if not got:
        return None
    frames = {s.frame: s.refined for s in got}
    return RefinedPose(psnr=float(np.mean([min(PSNR_CAP, s.refined.psnr) for s in got])),
                       ssim=float(np.mean([s.refined.ssim for s in got])),
                       plain_psnr=float(np.mean([min(PSNR_CAP, s.psnr) for s in got])), images=len(got), steps=steps,
                       shift_cm=float(np.mean([r.shift_cm for r in frames.values()])),
                       max_angle_deg=float(max(r.max_angle_deg for r in frames.values())),
                       seconds=round(seconds, 3), protocol=protocol, target=target)


@dataclass(frozen=True)
class ScoredModel:
    """The avatar that was scored (metrics.json "model")."""

    variant: str
    latent: str
    use_delta_n: bool
    use_embedding: bool
    ablations: list[str]  # the fit's --ablation switches

    @property
    def label(self) -> str:
        """What distinguishes it from the full model ("full model" when nothing does)."""
        parts = list(self.ablations)
        if not parts:
            if self.variant != "slrf":
                parts.append(self.variant)
            if not self.use_delta_n:
                parts.append("no-delta-n")
            if not self.use_embedding:
                parts.append("no-embedding")
            if self.latent != "cvae":
                parts.append(f"latent={self.latent}")
        return ", ".join(parts) if parts else "full model"


@dataclass(frozen=True)
class EvalMetrics:
    """`eval/<name>/metrics.json`, field for field."""

    schema_version: int
    split: str
    protocol: str
    psnr: float  # mean over (frame, view) images of the per-image PSNR, dB
    ssim: float
    lpips: float | None  # None when LPIPS is unavailable (see lpips_reason)
    lpips_reason: str
    psnr_std: float | None
    psnr_min: float | None
    psnr_max: float | None
    ssim_std: float | None
    images: int
    frames: list[int]
    views: list[str]
    every: int
    averaging: str
    checkpoint_step: int
    checkpoint: str | None
    background: list[float]
    ground_truth: str
    latent: str
    protocol_details: str
    metric_settings: dict[str, Any]
    model: ScoredModel
    image_size: list[int]  # [W, H]
    timing: dict[str, Any]
    config: dict[str, Any]  # EvalConfig.to_json()
    created: str
    region: str = "all"  # what `psnr` is computed over: all (the protocol's region) | garment | body
    regions: dict[str, Any] | None = None  # per region: RegionScore as a dict (with ground-truth geometry only)
    benchmark: str | None = None  # the named benchmark protocol scored under (avatarctl.evaluate.benchmarks), if any
    comparable_with: list[str] | None = None  # the published figures that protocol is set beside
    not_comparable: list[str] | None = None  # why this figure is not the protocol's in full ([]: it is)
    colour_matched: dict[str, Any] | None = None  # ColourMatched as a dict: NeRF-W's colour-matched score (issue 51)
    test_project: str | None = None  # the project whose images were scored when not this one (`--test-project`)
    camera_colour: dict[str, Any] | None = None  # held-out cameras rendered through ingest's colour gains (issue 51)
    refined_pose: dict[str, Any] | None = None  # RefinedPose as a dict: scored after test-time pose refinement
    held_out_poses: dict[str, Any] | None = None  # the held-out frames driven by the fit's poses (fit/held_out_poses)

    def to_json(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> "EvalMetrics":
        # absent from metrics.json written before `--region`, the benchmark protocols, `--test-project` or issue 51
        optional = {"region", "regions", "benchmark", "comparable_with", "not_comparable", "test_project",
                    "colour_matched", "camera_colour", "refined_pose", "held_out_poses"}
        kw = {f.name: d[f.name] for f in fields(cls) if f.name in d or f.name not in optional}
        kw["model"] = ScoredModel(**{f.name: d["model"][f.name] for f in fields(ScoredModel)})
        return cls(**kw)

    @property
    def pairs(self) -> set[tuple[int, str]]:
        """The (frame, view) images scored."""
        return {(int(f), str(v)) for f in self.frames for v in self.views}


@dataclass(frozen=True)
class RegionScore:
    """One region's score over an eval (metrics.json "regions"[name])."""

    psnr: float | None  # mean over images of the per-image PSNR over the region (images where it is empty skipped)
    pooled_psnr: float | None  # PSNR of the squared error pooled over every region pixel of every image
    images: int  # images where the region is not empty
    pixels: int  # region pixels over all images
    share_of_pixels: float  # of the protocol's region
    share_of_error: float  # of the squared error summed over the protocol's region
    flat_colour_psnr: float | None  # mean over images of the PSNR of the region's best flat colour (a floor)


def region_scores(scores: list[ImageScore]) -> dict[str, RegionScore] | None:
    """Per-region summary of the images' `region_mse` / `region_pixels` (None without ground-truth geometry)."""
    from avatarctl.evaluate.metrics import psnr_from_mse

    if not scores or scores[0].region_mse is None:
        return None
    total_err = sum(s.mse * s.pixels for s in scores)
    total_px = sum(s.pixels for s in scores)
    out = {}
    for name in scores[0].region_pixels:
        got = [(s.region_mse[name], s.region_pixels[name]) for s in scores if s.region_pixels[name] > 0]
        flat = [min(PSNR_CAP, psnr_from_mse(s.region_mse[f"{name}_flat"])) for s in scores
                if s.region_pixels[name] > 0]
        err = sum(m * n for m, n in got)
        px = sum(n for _, n in got)
        db = [min(PSNR_CAP, psnr_from_mse(m)) for m, _ in got]
        out[name] = RegionScore(psnr=sum(db) / len(db) if db else None,
                                pooled_psnr=min(PSNR_CAP, psnr_from_mse(err / px)) if px and err > 0 else None,
                                images=len(got), pixels=px, share_of_pixels=px / max(total_px, 1),
                                share_of_error=err / total_err if total_err > 0 else 0.0,
                                flat_colour_psnr=sum(flat) / len(flat) if flat else None)
    return out


def per_frame_csv(scores: list[ImageScore]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    from avatarctl.evaluate.metrics import psnr_from_mse

    names = list(scores[0].region_pixels) if scores and scores[0].region_pixels is not None else []
    w.writerow(["frame", "view", "psnr", "ssim", "mse", "mse_r", "mse_g", "mse_b", "pixels", "matched_psnr",
                "matched_plain_psnr",
                "refined_psnr", "refined_ssim", "latent", "render_seconds"]
               + [f"{n}_{k}" for n in names for k in ("psnr", "pixels")])
    for s in scores:
        extra = []
        for n in names:
            m = s.region_mse[n]
            extra += [f"{min(PSNR_CAP, psnr_from_mse(m)):.4f}" if s.region_pixels[n] else "", s.region_pixels[n]]
        matched = ["", ""] if s.matched is None else [f"{min(PSNR_CAP, psnr_from_mse(e)):.4f}"
                                                      for e in (s.matched.mse, s.matched.plain_mse)]
        refined = ["", ""] if s.refined is None else [f"{min(s.refined.psnr, PSNR_CAP):.4f}",
                                                       f"{s.refined.ssim:.6f}"]
        channels = ["", "", ""] if s.mse_rgb is None else [f"{e:.8f}" for e in s.mse_rgb]
        w.writerow([s.frame, s.view, f"{min(s.psnr, PSNR_CAP):.4f}", f"{s.ssim:.6f}", f"{s.mse:.8f}"] + channels
                   + [s.pixels] + matched + refined + [s.latent, f"{s.seconds:.3f}"] + extra)
    return buf.getvalue()


def read_per_frame_csv(path: str | Path) -> list[dict[str, Any]]:
    """Rows of a `per_frame.csv` with numbers parsed."""
    rows = []
    with open(path, newline="") as fh:
        for r in csv.DictReader(fh):
            rows.append({"frame": int(r["frame"]), "view": r["view"], "psnr": float(r["psnr"]),
                         "ssim": float(r["ssim"]), "mse": float(r["mse"]), "pixels": int(r["pixels"])})
    return rows
