"""Person masks and body fits (anny, SMPL, SMPL-X) estimated from the images, for captures that ship neither.

Steps (all in the undistorted, resized geometry of the project's pinhole cameras, so 2D points need no further
undistortion):

1. `detect_people`: MediaPipe Pose per camera over its frames in order (`avatarctl.ingest.keypoints`) -> 2D
   keypoints with confidences and, when asked, a person mask per view; `refine_masks` then corrects each mask's
   outline against the camera's background, estimated from its own frames (static cameras);
2. `estimate_fits`: robust multi-view triangulation of every keypoint (`avatarctl.geometry.triangulate`: RANSAC
   over view pairs, outlier views rejected by reprojection error, weighted DLT on the inliers); frames where fewer
   than `MIN_JOINTS` keypoints (or fewer than three of the four torso points) triangulate are skipped, never fitted;
3. the body model's fit to the 3D keypoints (`avatarctl.body.fit_keypoints`), one shape for the subject, anny's
   keypoints placed where MediaPipe puts them on a body (`detector_offsets`; `--no-keypoint-offsets`: anny's own),
   with a silhouette term when person masks are at hand (`silhouette_targets`: the capture's mask files or
   MediaPipe's person segmentation) that keeps the projected body inside them.

One video (`estimate_monocular`, one static camera): no triangulation; the body model is fitted to the 2D keypoints
and their confidences directly (`avatarctl.body.fit_keypoints`'s monocular energy: reprojection, the subject's
height as the scale prior, ground contact where the feet are seen, root smoothness, joint limits, the silhouette
term on MediaPipe's masks and its other side, the outline term, where the masks' outline lies close to the body).
Before it, `check_monocular` refuses a video without a person, with the person out of
frame in most frames, with several people (`several_people`: MediaPipe Pose tracks one person, so each sampled
frame is searched again with that person painted out), or from a moving camera (`camera_shift_px`: the background's
shift between frames by phase correlation).

Each step's figures land in `EstimateReport` (shown in the ingest summary and saved in the manifest).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np

from avatarctl.body.motion import BodyMotion
from avatarctl.progress import ProgressFn, ProgressReport

MIN_JOINTS = 8  # triangulated keypoints a frame needs to be fitted
REPROJ_THRESHOLD = 0.02  # inlier threshold of the triangulation, as a fraction of the image's larger side
MIN_THRESHOLD_PX = 4.0  # ... but at least this many pixels
MIN_CONFIDENCE = 0.5  # MediaPipe visibility below which a 2D keypoint is not used
# frames each camera's video-mode detector sees first (the 6th back to the 2nd), their results dropped: cold, it
# drops parts of the person on the first frames (synth realistic, the lowest quarter's recall on frame 0: 0.47 and
# 0.75 against 0.80 and 0.94 primed; docs/own_capture.md)
WARMUP_FRAMES = 5
DEFAULT_HEIGHT_M = 1.70  # the monocular fit's height prior when the user gives none (an adult's average, both sexes)
MONO_SILHOUETTE_WEIGHT = 10.0  # the monocular fit's silhouette weight (one view: the masks constrain depth-blind limbs)
# the monocular fit's outline weight (the silhouette term's other side; synth phone seeds 0 / 1, 300-s avatars: held-out
# frames +0.07 / +0.35 dB, training frames +0.11 / +0.63; at 10 the held-out frames +0.29 / +0.56, the training
# frames -0.08 / -0.76: docs/experiments/outline_term_2026-11-30/)
MONO_OUTLINE_WEIGHT = 3.0
MONO_GROUND_WEIGHT = 1.0  # λ_ground of the monocular fit
MONO_ROOT_SMOOTH = 1e-3  # λ_root of the monocular fit
MONO_POSE_WEIGHT = 3e-3  # λ_pose of the monocular fit (the 3D fit's 1e-5 leaves a limb's depth free; measured on the
# synthetic phone video, 13 frames, 200 steps: 1e-5 4.72, 1e-4 4.82, 1e-3 3.96, 3e-3 3.80, 1e-2 3.62 cm joint error
# while the reprojection error grows 2.65 -> 4.78 px: docs/experiments/phone_video_2026-11-27)
MASK_BAND = 0.007  # refined masks: the band about MediaPipe's outline that the plate decides, x the image diagonal
MIN_IN_VIEW = 0.5  # share of the frames in which the person must be usable (in frame, enough keypoints)
MIN_VIDEO_FRAMES = 10  # a video needs this many frames (after --frames): 2/3 train, 1/3 held out
PEOPLE_SAMPLES = 6  # frames searched for a second person
SECOND_PERSON_SHARE = 0.5  # ... a second person in at least this share of them -> several people
SHIFT_CONFIRM = 0.5  # a background shift counts where it leaves at most this share of the unshifted difference
MAX_CAMERA_SHIFT = 0.03  # background shift, as a fraction of the image diagonal, above which the camera moves

ReadView = Callable[[str, int], np.ndarray]  # (camera, frame) -> undistorted RGB uint8 [H, W, 3]
ReadMask = Callable[[str, int], np.ndarray]  # (camera, frame) -> undistorted person mask, bool [H, W]


@dataclass
class Detections:
    """2D detections of every (frame, camera)."""

    cams: list[str]
    frames: list[int]
    names: tuple[str, ...]  # keypoint names, [joints]
    keypoints: np.ndarray  # [frames, cams, joints, 2] pixels (undistorted geometry), NaN where not found
    confidence: np.ndarray  # [frames, cams, joints] in [0, 1]
    masks: dict[tuple[str, int], bytes] = field(default_factory=dict)  # (cam, frame) -> PNG of the bool mask
    enlarged: dict[str, list[int]] = field(default_factory=dict)  # cam -> frames detected again enlarged (not saved)

    @property
    def found(self) -> np.ndarray:
        """[frames, cams] bool: a person was detected."""
        return np.isfinite(self.keypoints).all(axis=-1).any(axis=-1)

    def mask(self, cam: str, frame: int) -> np.ndarray:
        """bool [H, W] person mask of one view (empty when none was found)."""
        import cv2

        return cv2.imdecode(np.frombuffer(self.masks[(cam, frame)], np.uint8), cv2.IMREAD_GRAYSCALE) > 0

    def save(self, path) -> None:
        """The keypoints and confidences as an npz, atomically (`cams`, `frames`, `names`, `keypoints` [frames, cams,
        joints, 2] undistorted pixels with NaN where not found, `confidence` [frames, cams, joints]); no masks."""
        from avatarctl.atomic import atomic_path

        with atomic_path(path) as tmp:
            with open(tmp, "wb") as fh:
                np.savez(fh, cams=np.array(self.cams, dtype=str), frames=np.asarray(self.frames, dtype=np.int64),
                         names=np.array(self.names, dtype=str), keypoints=self.keypoints.astype(np.float32),
                         confidence=self.confidence.astype(np.float32))

    @classmethod
    def load(cls, path) -> "Detections":
        """A `save`d npz (no masks); a one-line `InputError` when it is unreadable."""
        from avatarctl.errors import InputError

        try:
            with np.load(path, allow_pickle=False) as z:
                det = cls(cams=[str(c) for c in z["cams"]], frames=[int(f) for f in z["frames"]],
                          names=tuple(str(n) for n in z["names"]), keypoints=z["keypoints"].astype(np.float64),
                          confidence=z["confidence"].astype(np.float64))
        except (OSError, KeyError, ValueError) as e:
            raise InputError(f"bad keypoint detections: {e}", where=str(path),
                             fix="ingest the capture again (it writes ingest/keypoints.npz)") from None
        f, c, j = len(det.frames), len(det.cams), len(det.names)
        if det.keypoints.shape != (f, c, j, 2) or det.confidence.shape != (f, c, j):
            raise InputError(f"bad keypoint detections: keypoints {det.keypoints.shape}, confidence "
                             f"{det.confidence.shape} for {f} frames, {c} cameras, {j} keypoints", where=str(path),
                             fix="ingest the capture again (it writes ingest/keypoints.npz)")
        return det

    def mask_found(self, frame: int) -> bool:
        """Every camera has a non-empty person mask at `frame`."""
        import cv2

        for c in self.cams:
            m = cv2.imdecode(np.frombuffer(self.masks[(c, frame)], np.uint8), cv2.IMREAD_GRAYSCALE)
            if not m.any():
                return False
        return True


def detect_people(read_view: ReadView, cams: list[str], frames: list[int], masks: bool,
                  progress: ProgressFn | None = None, smooth: bool = False) -> Detections:
    """Run the detector on every view (camera-major: one tracker per camera stream, primed on the frames after the
    first, backwards: `WARMUP_FRAMES`). `smooth`: MediaPipe's temporal landmark filter (on for one video, off for
    calibrated cameras: `ingest.keypoints`, "Temporal smoothing"). A camera of small images with odd masks runs
    again on enlarged images (`odd_masks`; `ingest.keypoints`, "Small images")."""
    import cv2

    from avatarctl.ingest.keypoints import DETECT_MIN_SIDE, KEYPOINT_NAMES, PoseDetector

    J = len(KEYPOINT_NAMES)
    kp = np.full((len(frames), len(cams), J, 2), np.nan)
    conf = np.zeros((len(frames), len(cams), J))
    out = Detections(cams=list(cams), frames=list(frames), names=KEYPOINT_NAMES, keypoints=kp, confidence=conf)
    done, total = 0, len(frames) * len(cams)

    def stream(c: str, scale: float, on_frame=None) -> list[tuple[np.ndarray, np.ndarray, bytes, int]]:
        """Each frame's (keypoints, confidence, PNG of the mask, mask area): masks encoded as they come."""
        found = []
        with PoseDetector(masks=masks, scale=scale, smooth=smooth) as det:
            for f in frames[WARMUP_FRAMES:0:-1]:  # the tracker primed on the next frames, backwards to the first
                det(read_view(c, f))
            for f in frames:
                d = det(read_view(c, f))
                png = cv2.imencode(".png", d.mask.astype(np.uint8) * 255)[1].tobytes() if masks else b""
                found.append((d.keypoints, d.confidence, png, int(d.mask.sum()) if masks else 0))
                if on_frame is not None:
                    on_frame()
        return found

    def tick() -> None:
        nonlocal done
        done += 1
        if progress is not None:
            progress(ProgressReport(done=done, total=total, part="detect"))

    for ci, c in enumerate(cams):
        found = stream(c, 1.0, tick)
        area = np.array([a for *_, a in found], dtype=float)
        odd = odd_masks(area) if masks else np.zeros(len(frames), bool)
        short = min(read_view(c, frames[0]).shape[:2]) if odd.any() else DETECT_MIN_SIDE
        if short < DETECT_MIN_SIDE:
            again = stream(c, DETECT_MIN_SIDE / short)
            mended = odd & ~odd_masks(np.array([a for *_, a in again], dtype=float), reference=area)
            found = [a if m else d for d, a, m in zip(found, again, mended)]
            if mended.any():
                out.enlarged[c] = [f for f, m in zip(frames, mended) if m]
        for fi, (f, (k, cf, png, _)) in enumerate(zip(frames, found)):
            kp[fi, ci], conf[fi, ci] = k, cf
            if masks:
                out.masks[(c, f)] = png
    return out


def odd_masks(area: np.ndarray, reference: np.ndarray | None = None) -> np.ndarray:
    """[frames] bool: mask areas [frames] (pixels) more than `MASK_AREA_ODD` times off the median of the non-empty
    `reference` areas (default: `area` itself), either way; an empty mask is odd. A detector that lost the person
    (its mask the floor) leaves such masks."""
    from avatarctl.ingest.keypoints import MASK_AREA_ODD

    ref = area if reference is None else reference
    med = float(np.median(ref[ref > 0])) if (ref > 0).any() else 0.0
    if med == 0.0:
        return np.zeros(len(area), bool)
    return (area > MASK_AREA_ODD * med) | (area < med / MASK_AREA_ODD)


@dataclass(frozen=True)
class MaskRefinement:
    """What `refine_masks` did, per camera: the band it decided (px), the share of its pixels with a known plate and
    the share of the masks' pixels it changed (added or removed, over MediaPipe's mask area)."""

    band_px: dict[str, int]
    plate_known: dict[str, float]
    changed: dict[str, float]
    plate: dict[str, str] = field(default_factory=dict)  # camera -> "capture" (its background/<cam> image) or
    # "estimated" (from its frames)

    def to_json(self) -> dict:
        return {"band_px": self.band_px, "plate_known": {c: round(v, 4) for c, v in self.plate_known.items()},
                "changed": {c: round(v, 4) for c, v in self.changed.items()}, "plate": self.plate}


def refine_masks(det: Detections, read_view: ReadView, progress: ProgressFn | None = None,
                 plate_of: Callable[[str], np.ndarray | None] | None = None) -> tuple[Detections, MaskRefinement]:
    """`det` with every camera's MediaPipe masks refined against the camera's plate (`ingest.masks.refine_mask` on
    every frame, deciding a band of `MASK_BAND` x the image diagonal about MediaPipe's outline). The plate is the
    capture's own (`plate_of(camera)`: its undistorted background image, known everywhere; None where the camera has
    none; read one camera at a time) where it agrees with the
    plate estimated from the camera's frames (`ingest.masks.estimate_plate` over up to `PLATE_FRAMES` evenly spaced
    frames with a mask; `plate_agrees`), else that estimate. For static cameras (a rig; a phone on a tripod:
    `check_monocular`). A camera with no known plate pixel keeps MediaPipe's masks."""
    import cv2

    from avatarctl.ingest.masks import PLATE_FRAMES, estimate_plate, plate_agrees, refine_mask

    out = replace(det, masks=dict(det.masks))
    known_share, changed, bands, source = {}, {}, {}, {}
    done, total = 0, len(det.cams) * len(det.frames)
    for c in det.cams:
        with_mask = [f for f in det.frames if det.mask(c, f).any()]
        pick = [with_mask[i] for i in np.unique(np.linspace(0, len(with_mask) - 1, PLATE_FRAMES).round().astype(int))
                ] if with_mask else []
        if not pick:
            known_share[c], changed[c], bands[c] = 0.0, 0.0, 0
            done += len(det.frames)
            continue
        h, w = det.mask(c, pick[0]).shape
        band = bands[c] = max(2, int(round(MASK_BAND * np.hypot(h, w))))
        picked = {f: read_view(c, f) for f in pick}  # read once: the plate's frames are refined below too
        plate, known = estimate_plate(np.stack(list(picked.values())), np.stack([det.mask(c, f) for f in pick]), band)
        source[c] = "estimated"
        own = plate_of(c) if plate_of is not None else None
        if own is not None and plate_agrees(own, plate, known):
            plate, known, source[c] = own, np.ones_like(known), "capture"
        known_share[c], moved, area = float(known.mean()), 0, 0
        for f in det.frames:
            m = det.mask(c, f)
            if known.any() and m.any():
                rgb = picked.pop(f, None)  # each picked frame freed once refined
                r = refine_mask(read_view(c, f) if rgb is None else rgb, plate, known, m, band)
                moved, area = moved + int((r ^ m).sum()), area + int(m.sum())
                out.masks[(c, f)] = cv2.imencode(".png", r.astype(np.uint8) * 255)[1].tobytes()
            done += 1
            if progress is not None:
                progress(ProgressReport(done=done, total=total, part="masks"))
        changed[c] = moved / max(area, 1)
    return out, MaskRefinement(band_px=bands, plate_known=known_share, changed=changed, plate=source)


@dataclass(frozen=True)
class EstimateReport:
    """Figures of the estimation steps (what the ingest summary shows)."""

    frames_detected: int  # frames with a person in at least two views
    frames_total: int
    views_with_person: float  # fraction of (frame, camera) views with a detection
    frames_skipped: list[int]  # frames left out: not fitted (no person / too few keypoints) or in `frames_no_mask`
    mean_reprojection_px: float  # over triangulated keypoints and their inlier views
    views_rejected: float  # fraction of confident 2D keypoints rejected as outliers by the triangulation
    keypoints_triangulated: float  # fraction of (fitted frame, keypoint) triangulated
    fit_error_cm: float  # mean distance of the fitted keypoints to the triangulated ones
    fit_seconds: float
    body_model: str = "anny"  # the body model fitted
    frames_no_mask: list[int] = field(default_factory=list)  # frames where a view had no person mask (masks mediapipe)
    monocular: bool = False  # one video: fitted to the 2D keypoints (no triangulation)
    height_m: float = float("nan")  # monocular: the fitted subject's height (metres)
    height_prior: str = ""  # monocular: the height prior and where it came from
    ground: list[float] | None = None  # monocular: the fitted floor plane n·x = d, [nx, ny, nz, d] (world = camera)
    silhouette_inside_before: float = float("nan")  # share of projected vertices inside the masks when the
    silhouette_inside_after: float = float("nan")  # silhouette term switched on / at the end (NaN: term off)
    outline_before_cm: float = float("nan")  # the masks' outline's mean distance to the projected body when the
    outline_after_cm: float = float("nan")  # outline term switched on / at the end, cm at the subject (NaN: off)
    outline_on: bool = False  # the outline term ran (off: weight 0, or its gate found loose clothing)
    keypoint_offsets: bool = False  # the fit placed anny's keypoints where MediaPipe puts them
    masks_refined: MaskRefinement | None = None  # MediaPipe's masks refined against estimated plates (`refine_masks`)
    detected_enlarged: dict[str, list[int]] = field(default_factory=dict)  # `Detections.enlarged`

    def rows(self, fitted: bool) -> list[tuple[str, str]]:
        """(item, value) lines for the ingest summary; `fitted`: the fits were estimated (else masks only)."""
        out = [("person detected", f"{self.frames_detected}/{self.frames_total} frames" if self.monocular else
                f"{self.frames_detected}/{self.frames_total} frames (2+ views), "
                f"{100 * self.views_with_person:.1f}% of views")]
        if self.frames_skipped:
            n_fit = len(self.frames_skipped) - len(self.frames_no_mask)
            why = ([f"{n_fit} without a person or enough keypoints"] if n_fit else []) + \
                  ([f"{len(self.frames_no_mask)} without a person mask in some view"] if self.frames_no_mask else [])
            shown = ", ".join(str(f) for f in self.frames_skipped[:8])
            shown += " …" if len(self.frames_skipped) > 8 else ""
            out.append(("frames skipped", f"{'; '.join(why)}: {shown}"))
        if fitted and self.monocular:
            out.append((f"{self.body_model} fit (monocular)", f"{self.mean_reprojection_px:.2f} px mean reprojection "
                                                              f"error ({self.fit_seconds:.0f} s)"
                        + (", MediaPipe's keypoint offsets" if self.keypoint_offsets else "")))
            out.append(("height", f"{self.height_m:.2f} m fitted ({self.height_prior})"))
            out.append(("floor", "feet not seen: no ground contact" if self.ground is None else
                        f"normal ({self.ground[0]:+.2f}, {self.ground[1]:+.2f}, {self.ground[2]:+.2f}), "
                        f"camera {-self.ground[3]:.2f} m above it (world = camera frame, +y down)"))
        elif fitted:
            out.append(("triangulation", f"{self.mean_reprojection_px:.2f} px mean reprojection error, "
                                         f"{100 * self.views_rejected:.1f}% of 2D keypoints rejected as outliers, "
                                         f"{100 * self.keypoints_triangulated:.1f}% of keypoints triangulated"))
            out.append((f"{self.body_model} keypoint fit", f"{self.fit_error_cm:.2f} cm mean keypoint error "
                                             f"({self.fit_seconds:.0f} s)"
                                             + (", MediaPipe's keypoint offsets" if self.keypoint_offsets else "")))
        if fitted:
            out.extend(self._silhouette_rows())
        if self.detected_enlarged:
            from avatarctl.ingest.keypoints import DETECT_MIN_SIDE

            cams = ", ".join(f"{c} ({len(f)} frames)" for c, f in self.detected_enlarged.items())
            out.append(("detected again", f"{cams}: odd masks (the person lost) detected on the images enlarged to "
                                          f"{DETECT_MIN_SIDE} px"))
        if self.masks_refined is not None:
            r = self.masks_refined
            lo, hi = (f"{100 * f(r.plate_known.values()):.0f}" for f in (min, max))
            known = lo if lo == hi else f"{lo}-{hi}"
            changed = 100 * float(np.mean(list(r.changed.values())))
            own = sorted(c for c, v in r.plate.items() if v == "capture")
            against = ("the capture's plates" if own and len(own) == len(r.plate) else
                       f"the capture's plates ({', '.join(own)}), else plates estimated from the frames" if own else
                       "plates estimated from the frames")
            out.append(("masks refined", f"against {against} ({known}% of each image known): "
                                         f"{changed:.1f}% of the mask pixels changed"))
        return out

    def _silhouette_rows(self) -> list[tuple[str, str]]:
        out = []
        if np.isfinite(self.silhouette_inside_after):
            out.append(("silhouette term", f"{100 * self.silhouette_inside_before:.1f}% -> "
                                           f"{100 * self.silhouette_inside_after:.1f}% of projected vertices "
                                           "inside the masks"))
        if self.outline_on:
            out.append(("outline term", f"the masks' outline {self.outline_before_cm:.1f} -> "
                                        f"{self.outline_after_cm:.1f} cm from the projected body (mean)"))
        elif np.isfinite(self.outline_after_cm):  # the weight was set, the gate kept the term off
            from avatarctl.body.fit_keypoints import OUTLINE_GATE_M

            out.append(("outline term", f"off: the masks' outline lies {self.outline_before_cm:.1f} cm from the "
                                        f"projected body on average (over {100 * OUTLINE_GATE_M:.1f}: loose "
                                        "clothing, whose outline would pull the limbs apart)"))
        return out

    def to_json(self) -> dict:
        """JSON-ready figures (NaN, for the steps that did not run, becomes null)."""
        def num(x: float, nd: int):
            return None if not np.isfinite(x) else round(float(x), nd)

        return {"frames_detected": self.frames_detected, "frames_total": self.frames_total,
                "views_with_person": num(self.views_with_person, 4), "frames_skipped": self.frames_skipped,
                "frames_no_mask": self.frames_no_mask, "mean_reprojection_px": num(self.mean_reprojection_px, 3),
                "views_rejected": num(self.views_rejected, 4),
                "keypoints_triangulated": num(self.keypoints_triangulated, 4),
                "fit_error_cm": num(self.fit_error_cm, 3), "fit_seconds": num(self.fit_seconds, 1),
                "body_model": self.body_model,
                "silhouette_inside_before": num(self.silhouette_inside_before, 4),
                "silhouette_inside_after": num(self.silhouette_inside_after, 4),
                "outline_before_cm": num(self.outline_before_cm, 2), "outline_after_cm": num(self.outline_after_cm, 2),
                "outline_on": self.outline_on,
                "keypoint_offsets": self.keypoint_offsets, "monocular": self.monocular,
                "height_m": num(self.height_m, 3), "height_prior": self.height_prior,
                "ground": None if self.ground is None else [round(float(g), 4) for g in self.ground],
                "masks_refined": None if self.masks_refined is None else self.masks_refined.to_json(),
                "detected_enlarged": self.detected_enlarged}


@dataclass(frozen=True)
class EstimatedFits:
    motion: BodyMotion | None  # rows = the kept frames (None when fits were not estimated)
    kept: list[int]  # frames kept, ascending
    report: EstimateReport


def silhouette_report(report) -> dict[str, float | bool]:
    """The `EstimateReport` fields of a keypoint fit's `SilhouetteReport` (None: the terms were off)."""
    if report is None:
        return {}
    return dict(silhouette_inside_before=report.inside_before, silhouette_inside_after=report.inside_after,
                outline_before_cm=100 * report.outline_before_m, outline_after_cm=100 * report.outline_after_m,
                outline_on=report.outline_on)


def silhouette_targets(cameras, cams: list[str], frames: list[int], read_mask: ReadMask):
    """`SilhouetteTargets` of `frames` for the pinhole `cameras` (order of `cams`): the distance field of every
    view's mask; a view whose mask is empty is left out (weight 0)."""
    from avatarctl.body.fit_keypoints import SilhouetteTargets, field_grid, mask_distance
    from avatarctl.geometry.triangulate import projection_matrices

    grid = field_grid(cameras[0].width, cameras[0].height)
    dist = np.zeros((len(frames), len(cams), *grid), dtype=np.float32)
    weight = np.zeros((len(frames), len(cams)))
    for fi, f in enumerate(frames):
        for ci, c in enumerate(cams):
            m = read_mask(c, f)
            if m.any():
                dist[fi, ci], weight[fi, ci] = mask_distance(m, grid), 1.0
    return SilhouetteTargets(P=projection_matrices(cameras),
                             image_size=np.array([[c.width, c.height] for c in cameras], dtype=np.float64),
                             focal_px=np.array([(c.K[0, 0] + c.K[1, 1]) / 2 for c in cameras]), distance=dist,
                             weight=weight)


def detector_offsets(body, on: bool = True):
    """MediaPipe's keypoint definitions against the body model's keypoints for the keypoint fit
    (`ingest.keypoints.MEDIAPIPE_ANNY_OFFSETS`): anny's when `on`; None otherwise and for SMPL / SMPL-X (not
    measured: their keypoints are the joint regressor's)."""
    from avatarctl.ingest.keypoints import MEDIAPIPE_ANNY_OFFSETS

    return MEDIAPIPE_ANNY_OFFSETS if on and body.name == "anny" else None


def triangulate_detections(det: Detections, cameras):
    """Every keypoint of every frame triangulated from the views that saw it (`geometry.triangulate
    .triangulate_robust`, the inlier threshold `REPROJ_THRESHOLD` of the image's larger side, at least
    `MIN_THRESHOLD_PX`; 2D keypoints under `MIN_CONFIDENCE` unused) with the pinhole `cameras` (order of `det.cams`):
    its rows are frame-major, [frames x joints]."""
    from avatarctl.geometry.triangulate import projection_matrices, triangulate_robust

    nf, nc, J, _ = det.keypoints.shape
    side = max(max(c.width, c.height) for c in cameras)
    x = det.keypoints.transpose(0, 2, 1, 3).reshape(nf * J, nc, 2)
    cf = det.confidence.transpose(0, 2, 1).reshape(nf * J, nc)
    return triangulate_robust(projection_matrices(cameras), x, cf, threshold_px=max(MIN_THRESHOLD_PX,
                              REPROJ_THRESHOLD * side), min_conf=MIN_CONFIDENCE)


def estimate_fits(det: Detections, cameras, body, fit_iters: int, fps: float,
                  progress: ProgressFn | None = None, read_mask: ReadMask | None = None,
                  silhouette_weight: float | None = None, limit_weight: float | None = None,
                  offsets: bool = True, outline_weight: float | None = None) -> EstimatedFits:
    """Triangulate the detections with the pinhole `cameras` (order of `det.cams`) and fit `body` (an `AnnyBody`
    or `SmplBody`) to the frames with enough keypoints. With `read_mask` the fit has a silhouette term of weight
    `silhouette_weight` and an outline term of weight `outline_weight` (None: the keypoint fit's defaults; 0: off);
    `limit_weight`: the joint limits' weight (None:
    the default); `offsets`: anny's keypoints where the detector puts them (`detector_offsets`). See the module
    docstring."""
    from avatarctl.body.fit_keypoints import TORSO, KeypointFitConfig, KeypointTargets, fit_keypoints, keypoint_body
    from avatarctl.ingest.keypoints import KEYPOINT_WEIGHTS

    nf, nc, J, _ = det.keypoints.shape
    tri = triangulate_detections(det, cameras)
    valid = tri.valid.reshape(nf, J)
    X = tri.X.reshape(nf, J, 3)
    torso = np.array([n in TORSO for n in det.names])
    ok = (valid.sum(1) >= MIN_JOINTS) & (valid[:, torso].sum(1) >= 3)
    kept = [f for f, k in zip(det.frames, ok) if k]
    n_cand = tri.candidates.sum()
    report = dict(body_model=body.name, frames_detected=int((det.found.sum(1) >= 2).sum()), frames_total=nf,
                  views_with_person=float(det.found.mean()) if det.found.size else 0.0,
                  frames_skipped=[f for f, k in zip(det.frames, ok) if not k],
                  mean_reprojection_px=float(np.nanmean(tri.error_px)) if tri.valid.any() else float("nan"),
                  views_rejected=float(tri.rejected.sum() / n_cand) if n_cand else 0.0,
                  keypoints_triangulated=float(valid[ok].mean()) if ok.any() else 0.0)
    if not ok.any():
        return EstimatedFits(None, [], EstimateReport(**report, fit_error_cm=float("nan"), fit_seconds=0.0))
    w = np.where(valid[ok], 1.0, 0.0) * KEYPOINT_WEIGHTS[None]
    targets = KeypointTargets(names=det.names, points=np.nan_to_num(X[ok]), weight=w)
    cfg = KeypointFitConfig(iters=fit_iters)
    if silhouette_weight is not None:
        cfg = replace(cfg, w_silhouette=float(silhouette_weight))
    if outline_weight is not None:
        cfg = replace(cfg, w_outline=float(outline_weight))
    if limit_weight is not None:
        cfg = replace(cfg, w_limits=float(limit_weight))
    sil = None
    if read_mask is not None and (cfg.w_silhouette > 0 or cfg.w_outline > 0):
        sil = silhouette_targets(cameras, det.cams, kept, read_mask)
    table = detector_offsets(body, offsets)
    fit = fit_keypoints(keypoint_body(body, det.names, table), targets, cfg, silhouettes=sil, progress=progress)
    wsum = (targets.select(fit.names).weight > 0).sum(1)
    err = float((fit.error_m * wsum).sum() / wsum.sum())
    report.update(silhouette_report(fit.silhouette))
    return EstimatedFits(fit.to_motion(kept, fps=fps), kept,
                         EstimateReport(**report, fit_error_cm=100 * err, fit_seconds=fit.seconds,
                                        keypoint_offsets=table is not None))


def usable_frames(det: Detections) -> np.ndarray:
    """[frames] bool: the first camera sees the person with `MIN_JOINTS` confident keypoints, 3 of them torso."""
    from avatarctl.body.fit_keypoints import TORSO

    conf = det.confidence[:, 0] >= MIN_CONFIDENCE  # [frames, joints]
    torso = np.array([n in TORSO for n in det.names])
    return (conf.sum(1) >= MIN_JOINTS) & (conf[:, torso].sum(1) >= 3)


def several_people(read_view: Callable[[int], np.ndarray], det: Detections) -> int:
    """How many of up to `PEOPLE_SAMPLES` frames with a person show a second one: the tracked person's mask
    (dilated) is painted grey and a fresh, static MediaPipe Pose searches the image again; a second person counts
    when its torso is confident, 80 % of its confident keypoints lie outside the painted region and it is at least
    half as tall as the first."""
    import cv2

    from avatarctl.ingest.keypoints import PoseDetector

    found = np.nonzero(det.found[:, 0])[0]
    picks = found[np.unique(np.linspace(0, len(found) - 1, min(PEOPLE_SAMPLES, len(found))).round().astype(int))] \
        if len(found) else []
    hits = 0
    torso = [det.names.index(n) for n in ("left_shoulder", "right_shoulder", "left_hip", "right_hip")]
    with PoseDetector(masks=False, static=True) as again:
        for fi in picks:
            rgb = read_view(det.frames[fi]).copy()
            m = det.mask(det.cams[0], det.frames[fi]) if det.masks else np.zeros(rgb.shape[:2], bool)
            pts = det.keypoints[fi, 0][np.isfinite(det.keypoints[fi, 0]).all(-1)]
            if not m.any():  # no mask: the keypoints' bounding box, padded
                x0, y0 = pts.min(0) - 0.15 * np.ptp(pts, 0)
                x1, y1 = pts.max(0) + 0.15 * np.ptp(pts, 0)
                m[max(int(y0), 0):max(int(y1), 0), max(int(x0), 0):max(int(x1), 0)] = True
            k = max(3, rgb.shape[0] // 40)
            m = cv2.dilate(m.astype(np.uint8), np.ones((k, k), np.uint8)) > 0
            rgb[m] = 127
            d = again(rgb)
            if not d.found or (d.confidence[torso] >= 0.7).sum() < 3:
                continue
            other = d.keypoints[d.confidence >= MIN_CONFIDENCE]
            ij = np.clip(np.round(other).astype(int), 0, [m.shape[1] - 1, m.shape[0] - 1])
            outside = ~m[ij[:, 1], ij[:, 0]]  # a phantom found in the painted-out person is no second person
            if outside.mean() >= 0.8 and np.ptp(other[:, 1]) >= 0.5 * np.ptp(pts[:, 1]):
                hits += 1
    return hits if len(picks) and hits >= SECOND_PERSON_SHARE * len(picks) else 0


def camera_shift_px(read_view: Callable[[int], np.ndarray], det: Detections) -> float:
    """The largest shift (pixels) of the background between the first frame with a person and up to
    `PEOPLE_SAMPLES` later ones: phase correlation (`cv2.phaseCorrelate`, Hann window) of the grey images with the
    person (its dilated mask) filled by the background's mean. A static camera gives ~0; a pan or a walk does not.
    A shift counts only where it explains the background better than no shift does (the mean absolute difference
    of the background pixels seen in both frames at most `SHIFT_CONFIRM` of the unshifted one): on a periodic
    background (a striped curtain) phase correlation can peak a period away although the camera stands still."""
    import cv2

    found = np.nonzero(det.found[:, 0])[0]
    if len(found) < 2 or not det.masks:
        return 0.0
    picks = found[np.unique(np.linspace(0, len(found) - 1, min(PEOPLE_SAMPLES + 1, len(found))).round().astype(int))]

    def grey(fi: int) -> tuple[np.ndarray, np.ndarray]:
        g = cv2.cvtColor(read_view(det.frames[fi]), cv2.COLOR_RGB2GRAY).astype(np.float32)
        m = det.mask(det.cams[0], det.frames[fi]).astype(np.uint8)
        k = max(3, g.shape[0] // 30)
        m = cv2.dilate(m, np.ones((k, k), np.uint8)) > 0
        g[m] = g[~m].mean() if (~m).any() else 0.0
        return g, ~m

    def background_difference(g0, b0, g, b) -> float:
        both = b0 & b
        return float(np.abs(g - g0)[both].mean()) if both.any() else float("inf")

    first, bg0 = grey(picks[0])
    window = cv2.createHanningWindow(first.shape[::-1], cv2.CV_32F)
    shifts = [0.0]
    for fi in picks[1:]:
        g, bg = grey(fi)
        (dx, dy), _ = cv2.phaseCorrelate(first.copy(), g.copy(), window)  # OpenCV 5.0.0 windows its inputs in place
        back = np.float32([[1, 0, -dx], [0, 1, -dy]])
        h, w = g.shape
        g_back = cv2.warpAffine(g, back, (w, h), flags=cv2.INTER_LINEAR)
        bg_back = cv2.warpAffine(bg.astype(np.uint8), back, (w, h), flags=cv2.INTER_NEAREST) > 0
        still = background_difference(first, bg0, g, bg)
        if background_difference(first, bg0, g_back, bg_back) <= SHIFT_CONFIRM * still:
            shifts.append(float(np.hypot(dx, dy)))
    return max(shifts)


def check_monocular(det: Detections, read_view: Callable[[int], np.ndarray], where: str) -> np.ndarray:
    """One-line errors for a video that cannot make an avatar (no person; the person out of frame, or too small,
    in most frames; several people; a moving camera). Returns `usable_frames`."""
    from avatarctl.errors import InputError

    n = len(det.frames)
    usable = usable_frames(det)
    if not det.found.any():
        raise InputError(f"no person found in the video ({n} frames searched)", where=where,
                         fix="film one person, whole body in frame and at least ~100 px tall (docs/own_capture.md)")
    if usable.sum() < MIN_IN_VIEW * n:
        raise InputError(f"the person is out of frame (or too small) in most of the video: usable in "
                         f"{int(usable.sum())} of {n} frames", where=where,
                         fix="keep the whole body in frame all the time, or select the good part with --frames")
    hits = several_people(read_view, det)
    if hits:
        raise InputError(f"several people in the video (a second person in {hits} of the frames checked)",
                         where=where, fix="film one person alone, or crop the video to one person")
    h, w = det.mask(det.cams[0], det.frames[int(np.argmax(det.found[:, 0]))]).shape
    shift = camera_shift_px(read_view, det)
    if shift > MAX_CAMERA_SHIFT * np.hypot(w, h):
        raise InputError(f"the camera moves: the background shifts by {shift:.0f} px between frames", where=where,
                         fix="put the phone on a tripod or lean it against something; only the person may move")
    return usable


def estimate_monocular(det: Detections, camera, body, fit_iters: int, fps: float, usable: np.ndarray,
                       height_m: float | None = None, progress: ProgressFn | None = None,
                       read_mask: ReadMask | None = None, silhouette_weight: float | None = None,
                       offsets: bool = True, outline_weight: float | None = None) -> EstimatedFits:
    """Fit `body` to the 2D keypoints of ONE camera (`det.cams == [camera.name]`, pinhole `camera`) in the
    `usable` frames; `height_m`: the subject's height (None: `DEFAULT_HEIGHT_M`). See the module docstring."""
    from avatarctl.body.fit_keypoints import (ImageKeypointTargets, KeypointFitConfig, fit_keypoints,
                                              keypoint_body)
    from avatarctl.geometry.triangulate import projection_matrices
    from avatarctl.ingest.keypoints import KEYPOINT_WEIGHTS

    kept = [f for f, u in zip(det.frames, usable) if u]
    rows = np.nonzero(usable)[0]
    conf = det.confidence[rows]  # [kept, 1, joints]
    w = np.where(conf >= MIN_CONFIDENCE, conf, 0.0) * KEYPOINT_WEIGHTS[None, None]
    targets = ImageKeypointTargets(names=det.names, P=projection_matrices([camera]),
                                   focal_px=np.array([(camera.K[0, 0] + camera.K[1, 1]) / 2]),
                                   points=np.nan_to_num(det.keypoints[rows]), weight=w)
    w_sil = MONO_SILHOUETTE_WEIGHT if silhouette_weight is None else float(silhouette_weight)
    w_out = MONO_OUTLINE_WEIGHT if outline_weight is None else float(outline_weight)
    prior = ("given with --height" if height_m is not None else
             f"default {DEFAULT_HEIGHT_M:.2f} m; pass --height")
    height = DEFAULT_HEIGHT_M if height_m is None else float(height_m)
    cfg = KeypointFitConfig(iters=fit_iters, w_silhouette=w_sil, w_outline=w_out, height_m=height,
                            w_ground=MONO_GROUND_WEIGHT, w_root_smooth=MONO_ROOT_SMOOTH, w_pose=MONO_POSE_WEIGHT)
    sil = (silhouette_targets([camera], det.cams, kept, read_mask)
           if read_mask is not None and (w_sil > 0 or w_out > 0) else None)
    table = detector_offsets(body, offsets)
    fit = fit_keypoints(keypoint_body(body, det.names, table), targets, cfg, silhouettes=sil, progress=progress)
    n = len(det.frames)
    report = EstimateReport(
        frames_detected=int(det.found[:, 0].sum()), frames_total=n, views_with_person=float(det.found.mean()),
        frames_skipped=[f for f, u in zip(det.frames, usable) if not u],
        mean_reprojection_px=float(np.mean(fit.error_px)), views_rejected=float("nan"),
        keypoints_triangulated=float("nan"), fit_error_cm=100 * float(np.mean(fit.error_m)),
        fit_seconds=fit.seconds, body_model=body.name, monocular=True, height_m=fit.height_m,
        height_prior=f"{height:.2f} m, {prior}",
        ground=None if fit.ground is None else [float(g) for g in fit.ground],
        **silhouette_report(fit.silhouette),
        keypoint_offsets=table is not None)
    return EstimatedFits(fit.to_motion(kept, fps=fps), kept, report)
