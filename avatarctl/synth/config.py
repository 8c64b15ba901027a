"""`SynthConfig`: every knob of the synthetic capture, with named presets.

Sizes: `views` cameras on a ring around the subject; `train_frames` + `test_frames` written frames; square
images of `size` pixels. The cloth is simulated at `sim_fps` (30 Hz) and every `stride`-th simulated frame is
written, so a short preset still covers a whole choreography (walk, turn, twirl) in real time.

Settings of the paper's other experiments (`avatarctl reproduce`, docs/reproduce.md):
- `monocular` (PeopleSnapshot-like, the paper's Fig. 6): one training camera (cam00) and the subject turning in
  place through 360 degrees with the arms in an A-pose, no skirt; cam01..cam03 (90, 180, 270 degrees around) are
  evaluation-only cameras (`split.json` test views: ingest/fit never train on them); the test frames turn on with
  the arms lowered and the elbows and knees bent (held-out poses).
- `phone` (issue 31: what a user films with one phone): the `monocular` scene through a portrait camera (288 x 512
  px, no lens distortion) written as ONE video file, `OUT/video.mp4`, with no calibration, masks or fits beside it;
  the truth goes under `OUT/gt/` (`layout = "video"`, see `avatarctl.synth.capture`).
- `tight` (ZJU-MoCap-like, Tab. 2): the tiny choreography and cameras without the skirt (tight clothing); the
  every-third rule leaves 4 training views, as the paper's 4-view ZJU-MoCap protocol.

Imperfections of a real capture (issue 51; each 0 / "truth" in every preset but `realistic`, `IMPERFECTIONS`): cameras
that disagree in colour (`exposure_ev`, `white_balance`, `held_out_ev`), sensor noise (`noise_std`), stronger JPEG compression
(`jpeg_quality`), motion blur (`shutter_s`), masks and body fits left for ingest to estimate (`masks`, `fits`: MediaPipe
masks, keypoint-fitted anny) or written with errors (`fit_noise_*`). The geometry, cameras and textures never depend
on them: `clean_twin()` is the same capture without them (same seed, same scene), so every imperfection can be
measured against it. `realistic`: 4 cameras (3 train, 1 held out), all imperfections at once.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, fields, replace
from typing import Any

from avatarctl.errors import InputError

SCHEMA_VERSION = 1
GENERATOR_VERSION = "synth-1"

_PRESETS: dict[str, dict[str, Any]] = {
    # for other stages' unit tests: seconds, not minutes
    "micro": dict(views=4, train_frames=6, test_frames=4, size=64, stride=4, supersample=1, warmup_frames=12,
                  transition_frames=9, skirt_rings=12, skirt_segments=40, substeps=10, iterations=2),
    "tiny": dict(views=6, train_frames=24, test_frames=12, size=96, stride=5, supersample=2, substeps=12),
    # small: 2x2 rays per pixel, as a sensor integrates its pixel (at 1x1 the skirt's tartan aliases: the ground truth
    # blurred by 1 px matches itself on the skirt at 18.4 dB vs 21.1 dB at 2x2; docs/experiments/skirt_ceiling_*).
    # standard: 1x1 (smaller pixels; 2x2 would take ~4x its 25 min of rendering)
    "small": dict(views=12, train_frames=80, test_frames=40, size=256, stride=2, supersample=2, substeps=12),
    "standard": dict(views=20, train_frames=300, test_frames=150, size=512, stride=1, supersample=1),
    # the paper's other settings at tiny sizes (CPU minutes)
    "monocular": dict(views=4, train_views=1, motion="turn", garment="none", train_frames=24, test_frames=8,
                      size=96, stride=5, supersample=2),
    # one phone video (portrait, phone-like size), the truth under gt/ (issue 31)
    "phone": dict(views=4, train_views=1, motion="turn", garment="none", train_frames=40, test_frames=12,
                  size=512, width=288, stride=3, supersample=2, layout="video"),
    "tight": dict(views=6, garment="none", train_frames=24, test_frames=12, size=96, stride=5, supersample=2),
    # a capture that behaves like a real one (issue 51): 4 cameras (the every-third rule holds cam01 out), exposure
    # and white balance differing per camera (the held-out one 0.25 stops brighter than its draw: issue 51's capture,
    # whose renders were 17-20 % darker than the held-out images), sensor noise, JPEG, a 1/60 s shutter, masks and
    # fits left to ingest
    "realistic": dict(views=4, train_frames=24, test_frames=12, size=128, stride=5, supersample=2, exposure_ev=0.25,
                      white_balance=0.05, held_out_ev=0.25, noise_std=0.01, jpeg_quality=80, shutter_s=1 / 60,
                      masks="none", fits="none"),
}
# the imperfections of a real capture and their clean values (what `SynthConfig.clean_twin` sets)
IMPERFECTIONS: dict[str, Any] = {"exposure_ev": 0.0, "white_balance": 0.0, "held_out_ev": 0.0, "noise_std": 0.0,
                                 "jpeg_quality": 95,
                                 "shutter_s": 0.0, "masks": "truth", "fits": "truth", "fit_noise_deg": 0.0,
                                 "fit_noise_cm": 0.0, "fit_noise_corr_frames": 0.0}
MASKS = ("truth", "none")
FITS = ("truth", "none")
BLUR_SAMPLES = 5  # renders averaged over the shutter time (shutter_s > 0)
MOTIONS = ("choreography", "turn")
GARMENTS = ("skirt", "none")
LAYOUTS = ("easymocap", "video")
PRESETS = tuple(_PRESETS)


@dataclass(frozen=True)
class SynthConfig:
    """Configuration of one synthetic capture (frozen; validated on construction; saved in capture.json)."""

    preset: str = "tiny"
    """Name of the preset the values came from (recorded only)."""
    seed: int = 0
    """Seed of every random choice: body shape, motion variation, cameras, lens distortion, textures."""
    views: int = 6
    """Number of cameras (cam00, cam01, ...) on a ring around the subject."""
    train_frames: int = 24
    """Written frames of the training segment (walk, turn, twirl)."""
    test_frames: int = 12
    """Written frames of the novel-pose test segment (march, arm poses, opposite twirl)."""
    size: int = 96
    """Image height in pixels (and the width, unless `width` is set)."""
    width: int = 0
    """Image width in pixels; 0: square images (`size`)."""
    stride: int = 4
    """Write every `stride`-th simulated frame (the simulation always runs at `sim_fps`)."""
    supersample: int = 2
    """Rays per pixel along each axis (anti-aliasing); masks are coverage >= 0.5."""
    sim_fps: float = 30.0
    """Simulation and motion rate, frames per second."""
    warmup_frames: int = 36
    """Unwritten frames before frame 0: the body blends from the reference pose to the first pose while the
    skirt settles under gravity."""
    transition_frames: int = 24
    """Unwritten frames between the training and test segments (the body blends into the test choreography,
    so no written test frame repeats a training pose; the cloth keeps simulating)."""
    skirt_rings: int = 25
    """Skirt grid rows from waist to hem."""
    skirt_segments: int = 72
    """Skirt grid columns around the body."""
    substeps: int = 20
    """XPBD substeps per simulated frame."""
    iterations: int = 4
    """XPBD constraint iterations per substep."""
    jpeg_quality: int = 95
    """JPEG quality of the saved images and background plates."""
    fit_noise_deg: float = 0.0
    """Body fits written with per-frame noise (`body.perturb`): each joint rotation off by N(0, this^2) degrees.
    The true fits go to gt/motion.npz. 0 (and fit_noise_cm 0): exact fits."""
    fit_noise_cm: float = 0.0
    """Per-frame noise of the written root translation, N(0, this^2) centimetres per axis."""
    fit_noise_corr_frames: float = 0.0
    """0: the fit noise is independent per frame (jitter); > 0: it drifts over about this many frames, same RMS
    (`body.perturb`)."""
    motion: str = "choreography"
    """choreography: walk, turn, twirl (train) then march, raised arms, opposite twirl (test); turn: turning in
    place through 360 degrees in an A-pose (train, PeopleSnapshot-like) then on with lowered arms, bent elbows and
    knees (test)."""
    garment: str = "skirt"
    """skirt: the simulated loose skirt; none: tight clothing (body only, no cloth simulation)."""
    layout: str = "easymocap"
    """easymocap: the capture folder (calibration, images, masks, plates, fits); video: only `OUT/video.mp4` (the
    first camera, undistorted, its 35 mm-equivalent focal length in the file's metadata, as phones write it) and
    the truth under `OUT/gt/` (`gt/capture/`: the same render as an EasyMocap capture, every camera)."""
    train_views: int = 0
    """0: every third camera (cam01, cam04, ...) is held out, the rest train; k > 0: cam00 .. cam(k-1) train and
    every other camera is evaluation-only (split.json test views)."""
    exposure_ev: float = 0.0
    """Cameras that disagree in exposure: camera c's image is scaled by 2^e_c, e_c ~ N(0, this^2) stops (its own
    seeded stream; the plates too). The true gains go to capture.json ("camera_colour")."""
    white_balance: float = 0.0
    """Cameras that disagree in white balance: on top of the exposure, each channel of camera c scaled by 2^w_ck,
    w_ck ~ N(0, this^2) stops."""
    held_out_ev: float = 0.0
    """The evaluation-only cameras' (split.json test views) exposure, in stops, on top of their `exposure_ev` draw: a
    held-out camera that surely disagrees with the training ones (a real capture's held-out camera did: +0.25)."""
    noise_std: float = 0.0
    """Sensor noise: N(0, this^2) added to every pixel and channel (images in [0, 1], after the colour gains, before
    the 8-bit rounding and the JPEG), seeded per camera and frame."""
    shutter_s: float = 0.0
    """Motion blur: each image averages `BLUR_SAMPLES` renders over this exposure time (seconds) centred on the frame
    (the geometry interpolated linearly between written frames of the same segment); the masks stay the frame's own
    coverage (the truth at the frame's instant). 0: no blur."""
    masks: str = "truth"
    """truth: masks/ holds the true masks; none: the capture has no masks/ (the truth goes to gt/masks/): ingest
    estimates them (`--masks mediapipe`, or `background` from the plates)."""
    fits: str = "truth"
    """truth: motion.npz holds the fits (exact, or with `fit_noise_*`); none: the capture has no motion.npz (the
    truth goes to gt/motion.npz): ingest estimates them (`--fits keypoints`: MediaPipe keypoints, anny fitted)."""

    def __post_init__(self) -> None:
        checks = [
            (self.views >= 2, "views must be >= 2"),
            (self.train_frames >= 1 and self.test_frames >= 1, "train_frames and test_frames must be >= 1"),
            (16 <= self.size <= 4096, "size must be in [16, 4096]"),
            (self.width == 0 or 16 <= self.width <= 4096, "width must be 0 (square) or in [16, 4096]"),
            (self.layout in LAYOUTS, f"layout must be one of {', '.join(LAYOUTS)}"),
            (self.stride >= 1, "stride must be >= 1"),
            (1 <= self.supersample <= 4, "supersample must be in [1, 4]"),
            (self.sim_fps > 0, "sim_fps must be > 0"),
            (self.warmup_frames >= 2, "warmup_frames must be >= 2"),
            (self.transition_frames >= 1, "transition_frames must be >= 1"),
            (self.skirt_rings >= 4 and self.skirt_segments >= 12, "skirt needs >= 4 rings and >= 12 segments"),
            (self.substeps >= 1 and self.iterations >= 1, "substeps and iterations must be >= 1"),
            (1 <= self.jpeg_quality <= 100, "jpeg_quality must be in [1, 100]"),
            (0 <= self.seed < 2**32, "seed must be in [0, 2^32)"),
            (0 <= self.fit_noise_deg <= 30 and 0 <= self.fit_noise_cm <= 50 and 0 <= self.fit_noise_corr_frames <= 1000,
             "fit noise must be in [0, 30] degrees, [0, 50] cm and [0, 1000] frames"),
            (self.motion in MOTIONS, f"motion must be one of {', '.join(MOTIONS)}"),
            (self.garment in GARMENTS, f"garment must be one of {', '.join(GARMENTS)}"),
            (0 <= self.train_views < self.views, "train_views must be in [0, views) (0 = every third held out; "
                                                 "at least one camera must be left for evaluation)"),
            (0 <= self.exposure_ev <= 2 and 0 <= self.white_balance <= 1 and -2 <= self.held_out_ev <= 2,
             "exposure_ev must be in [0, 2] stops, white_balance in [0, 1] and held_out_ev in [-2, 2]"),
            (0 <= self.noise_std <= 0.2, "noise_std must be in [0, 0.2] (images in [0, 1])"),
            (0 <= self.shutter_s <= self.stride / self.sim_fps,
             f"shutter_s must be in [0, {self.stride / self.sim_fps:.3f}] seconds (at most one written frame)"),
            (self.masks in MASKS, f"masks must be one of {', '.join(MASKS)}"),
            (self.fits in FITS, f"fits must be one of {', '.join(FITS)}"),
            (self.fits == "truth" or not (self.fit_noise_deg or self.fit_noise_cm),
             "fit noise needs fits 'truth' (with fits 'none' ingest estimates the fits)"),
            (self.layout == "easymocap" or self.masks == self.fits == "truth",
             "masks / fits 'none' need the easymocap layout (the video layout writes neither)"),
        ]
        for ok, msg in checks:
            if not ok:
                raise InputError(f"invalid synth config: {msg}", fix="fix the option or use a --preset")

    @classmethod
    def preset(cls, name: str, seed: int = 0, **overrides: Any) -> "SynthConfig":
        """The named preset (`micro`, `tiny`, `small`, `standard`, `monocular`, `phone`, `tight`, `realistic`) with
        optional field overrides."""
        if name not in _PRESETS:
            raise InputError(f"unknown synth preset {name!r}", fix=f"use one of {', '.join(PRESETS)}")
        known = {f.name for f in fields(cls)}
        bad = sorted(set(overrides) - known)
        if bad:
            raise InputError(f"unknown synth config fields {bad}", fix=f"use fields of SynthConfig: {sorted(known)}")
        return replace(cls(preset=name, seed=seed, **_PRESETS[name]), **overrides)

    def clean_twin(self) -> "SynthConfig":
        """The same capture (seed, scene, cameras, textures) without any imperfection (`IMPERFECTIONS`)."""
        return replace(self, **IMPERFECTIONS)

    @property
    def imperfections(self) -> dict[str, Any]:
        """The imperfections this config has: {field: value} of those that differ from `IMPERFECTIONS`."""
        return {k: getattr(self, k) for k, clean in IMPERFECTIONS.items() if getattr(self, k) != clean}

    @property
    def image_width(self) -> int:
        """Image width in pixels (`width`, or `size` for square images)."""
        return self.width or self.size

    @property
    def frames(self) -> int:
        """Written frames, train + test."""
        return self.train_frames + self.test_frames

    @property
    def sim_frames(self) -> int:
        """Simulated frames after the warm-up (incl. the transition; the written ones are every `stride`-th)."""
        return self.frames * self.stride + self.transition_frames

    def to_json(self) -> dict[str, Any]:
        return {"schema_version": SCHEMA_VERSION, **asdict(self)}

    def dumps(self) -> str:
        return json.dumps(self.to_json(), indent=2)
