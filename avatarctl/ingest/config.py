"""`IngestConfig`: the frozen, validated configuration of one ingest run (saved in the project manifest)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from avatarctl.errors import InputError
from avatarctl.frames import parse_frame_spec

SCHEMA_VERSION = 1
FORMAT_CHOICES = ("auto", "easymocap", "zju", "thuman4", "peoplesnapshot", "colmap", "actorshq", "dna_rendering",
                  "4d_dress", "video")
BODY_MODEL_CHOICES = ("anny", "smpl", "smplx", "toy")
MASK_CHOICES = ("auto", "files", "background", "mediapipe")
FITS_CHOICES = ("auto", "files", "keypoints")


@dataclass(frozen=True)
class IngestConfig:
    capture: Path  # the raw capture folder (never modified)
    project: Path  # the project directory to create (must not exist, or be empty)
    format: str = "auto"  # capture layout; "auto" detects it (avatarctl.io.detect)
    body_model: str | None = None  # anny | smpl | smplx | toy; None: the body model the capture's fits are for
    body_model_path: Path | None = None  # SMPL / SMPL-X model file (.pkl / .npz); not needed for anny
    masks: str = "auto"  # files | background | mediapipe | auto (files if the capture has masks, else mediapipe if
    # installed, else background plates if every camera has one)
    fits: str = "auto"  # files | keypoints (MediaPipe keypoints -> triangulation -> body fit) | auto (files if any)
    keypoint_fit_iters: int = 400  # Adam steps of the keypoint fit (--fits keypoints; anny, smpl or smplx)
    keypoint_silhouette: float | None = None  # weight of the keypoint fit's silhouette term (None: the fit's default,
    # avatarctl.body.fit_keypoints.SILHOUETTE_WEIGHT; 0: off)
    keypoint_outline: float | None = None  # weight of its other side, the masks' outline pulling the body (None: the
    # fit's default: avatarctl.ingest.estimate.MONO_OUTLINE_WEIGHT for one video, else OUTLINE_WEIGHT; 0: off)
    keypoint_offsets: bool = True  # anny fits: anny's keypoints where MediaPipe puts them
    # (avatarctl.ingest.keypoints.MEDIAPIPE_ANNY_OFFSETS; False: anny's own COCO points)
    refine_masks: bool = True  # masks "mediapipe": refined against each camera's plate, the capture's or estimated
    # from its frames (avatarctl.ingest.estimate.refine_masks; static cameras)
    frames: str | None = None  # "start:stop[:step]" or "a,b,c" capture frame numbers (avatarctl.frames); None: all
    views: tuple[str, ...] | None = None  # camera names to ingest; None: every calibrated camera
    resize: float = 1.0  # scale factor applied after undistortion (e.g. 0.5)
    contact_sheet: bool = True  # write ingest/contact_sheet.png
    focal_px: float | None = None  # one video: the focal length in pixels of the video's frames (avatarctl.io.monocular)
    fov_deg: float | None = None  # one video: the diagonal field of view in degrees (instead of --focal-px)
    height_m: float | None = None  # one video: the subject's height in metres, the fit's scale prior (None: default)
    benchmark: str | None = None  # a named benchmark protocol (avatarctl.evaluate.benchmarks): its split, frames and
    # scale (avatarctl.ingest.benchmark); recorded in ingest/benchmark.json, which eval scores under by default
    schema_version: int = SCHEMA_VERSION

    def __post_init__(self) -> None:
        object.__setattr__(self, "capture", Path(self.capture))
        object.__setattr__(self, "project", Path(self.project))
        if self.body_model_path is not None:
            object.__setattr__(self, "body_model_path", Path(self.body_model_path))
        if self.format not in FORMAT_CHOICES:
            raise InputError(f"unknown --format {self.format!r}", fix=f"use one of {', '.join(FORMAT_CHOICES)}")
        if self.body_model is not None and self.body_model not in BODY_MODEL_CHOICES:
            raise InputError(f"unknown --body-model {self.body_model!r}",
                             fix=f"use one of {', '.join(BODY_MODEL_CHOICES)}")
        if self.masks not in MASK_CHOICES:
            raise InputError(f"unknown --masks {self.masks!r}", fix=f"use one of {', '.join(MASK_CHOICES)}")
        if self.fits not in FITS_CHOICES:
            raise InputError(f"unknown --fits {self.fits!r}", fix=f"use one of {', '.join(FITS_CHOICES)}")
        if self.keypoint_fit_iters < 0:
            raise InputError(f"--keypoint-fit-iters {self.keypoint_fit_iters} is negative", fix="use e.g. 400")
        if self.keypoint_silhouette is not None and not (math.isfinite(self.keypoint_silhouette)
                                                         and self.keypoint_silhouette >= 0):
            raise InputError(f"--keypoint-silhouette {self.keypoint_silhouette} must be a weight >= 0",
                             fix="use 0 to switch the silhouette term off, or leave the option out for the default")
        if self.keypoint_outline is not None and not (math.isfinite(self.keypoint_outline)
                                                      and self.keypoint_outline >= 0):
            raise InputError(f"--keypoint-outline {self.keypoint_outline} must be a weight >= 0",
                             fix="use 0 to switch the outline term off, or leave the option out for the default")
        if not (math.isfinite(self.resize) and 0.05 <= self.resize <= 4.0):
            raise InputError(f"--resize {self.resize} is out of range", fix="use a scale factor in [0.05, 4], e.g. 0.5")
        if self.views is not None:
            views = tuple(v.strip() for v in self.views if v.strip())
            if not views:
                raise InputError("--views is empty", fix="pass camera names separated by commas, e.g. 00,01")
            object.__setattr__(self, "views", views)
        if self.focal_px is not None and self.fov_deg is not None:
            raise InputError("--focal-px and --fov-deg both given", fix="give one of them")
        if self.focal_px is not None and not (math.isfinite(self.focal_px) and self.focal_px > 0):
            raise InputError(f"--focal-px {self.focal_px} must be a positive number of pixels", fix="e.g. 1500")
        if self.fov_deg is not None and not (math.isfinite(self.fov_deg) and 10 <= self.fov_deg <= 150):
            raise InputError(f"--fov-deg {self.fov_deg} is out of range", fix="give the diagonal field of view in "
                                                                               "degrees, in [10, 150], e.g. 78")
        if self.height_m is not None and not (math.isfinite(self.height_m) and 0.5 <= self.height_m <= 2.5):
            raise InputError(f"--height {self.height_m} is out of range", fix="give the person's height in metres, "
                                                                               "e.g. 1.75")
        if self.frames is not None:
            parse_frame_spec(self.frames)  # syntax check now; membership is checked against the capture later
        if self.benchmark is not None:
            from avatarctl.evaluate.benchmarks import benchmark

            benchmark(self.benchmark)  # a known name
            if self.resize != 1.0:
                raise InputError(f"--resize and --benchmark {self.benchmark} both set the image scale",
                                 fix="drop --resize: the protocol sets the scale")

    def to_json(self) -> dict[str, Any]:
        return {"schema_version": self.schema_version, "capture": str(self.capture.resolve()),
                "project": str(self.project.resolve()), "format": self.format, "body_model": self.body_model,
                "body_model_path": None if self.body_model_path is None else str(self.body_model_path.resolve()),
                "masks": self.masks, "fits": self.fits, "keypoint_fit_iters": self.keypoint_fit_iters,
                "keypoint_silhouette": self.keypoint_silhouette, "keypoint_outline": self.keypoint_outline,
                "frames": self.frames, "views": None if self.views is None else list(self.views),
                "resize": self.resize, "contact_sheet": self.contact_sheet, "focal_px": self.focal_px,
                "fov_deg": self.fov_deg, "height_m": self.height_m, "benchmark": self.benchmark}
