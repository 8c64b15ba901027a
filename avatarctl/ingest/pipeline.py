"""`run_ingest`: a raw capture -> a project directory (ingest stage).

Steps:
1. detect / read the capture (`avatarctl.ingest.readers`), select views and frames (with `--benchmark`, the named
   protocol's frames, held-out views and scale: `avatarctl.ingest.benchmark`), validate: cameras with
   images, complete frame grids for images and masks, fits for every frame, metres not millimetres;
2. convert the fits to the body model's `BodyMotion` (EasyMocap/ZJU Rh/Th -> SMPL global_orient/transl) — or,
   for a capture without fits (`--fits keypoints`) and/or without masks (`--masks mediapipe`), detect the person in
   every view and estimate anny / SMPL / SMPL-X fits and / or masks (`avatarctl.ingest.estimate`: MediaPipe's,
   refined against the capture's background plates or plates estimated from the frames);
   frames where no person is found are reported and left out — and pose the body mesh for every frame;
3. per frame and camera: undistort (and resize) the frame and mask — masks from the capture's files, from the
   background plate matted with the projected body mesh as seed (`--masks background`; `auto` without MediaPipe), or
   MediaPipe's person segmentation — and write them;
4. with 2+ cameras, every camera's colour gains from the posed body's colours across cameras on up to
   `COLOUR_FRAMES` training frames (`avatarctl.evaluate.colour.SharedColours`: exposure and white balance differ
   between cameras; `eval` shows a held-out camera through them);
5. write cameras (pinhole, dist = 0), body fits, split, camera colour, contact sheet, then the manifest.

The whole project is built in a temporary sibling directory and renamed into place at the end
(`avatarctl.atomic.atomic_dir`): a failure leaves nothing behind; the capture is only ever read.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from avatarctl.errors import InputError, ProjectError
from avatarctl.evaluate.colour import CameraGains, SharedColours
from avatarctl.frames import select_frames
from avatarctl.ingest.benchmark import BenchmarkPlan
from avatarctl.ingest.config import IngestConfig
from avatarctl.ingest.estimate import EstimateReport
from avatarctl.ingest.split import check_split_views
from avatarctl.io.capture import CaptureSource, check_complete, fmt_list
from avatarctl.progress import ProgressFn, ProgressReport

MIN_INSIDE = 0.90  # warn when fewer of the posed vertices than this project inside the masks
CAMERA_INSIDE = 0.5  # warn about a camera whose share of vertices inside its masks is under this x the cameras' median
POSE_CHUNK = 64  # frames posed at once
COLOUR_FRAMES = 12  # training frames the cross-camera colour estimate reads (spread evenly)
MAX_FOREGROUND = 0.99  # a mask with more foreground than this is inverted or blank, not a person in the frame


@dataclass
class IngestResult:
    project: Path
    format: str
    format_reason: str
    cameras: list[str]
    frames: list[int]
    resolution: tuple[int, int]  # (width, height) of the first camera after undistortion / resize
    body_model: str
    masks_source: str  # "files" | "background" | "mediapipe"
    seconds: float
    vertices_inside_masks: float  # mean fraction of posed mesh vertices projecting inside the masks
    fits_source: str = "files"  # "files" | "keypoints"
    estimate: EstimateReport | None = None  # figures of the detection / triangulation / fit steps, if run
    camera_colour: CameraGains | None = None  # every camera's colour gains (2+ cameras), ingest/camera_colour.json
    notes: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)


def _check_project_dest(cfg: IngestConfig) -> None:
    dest = cfg.project
    if dest.exists() and (not dest.is_dir() or any(dest.iterdir())):
        raise ProjectError("PROJECT already exists and is not empty", where=str(dest),
                           fix="choose a new PROJECT directory (ingest never overwrites one)")
    cap, proj = cfg.capture.resolve(), dest.resolve()
    if proj == cap or cap in proj.parents:
        raise ProjectError("PROJECT is inside the capture folder", where=str(dest),
                           fix="put the project outside CAPTURE: ingest never writes into the capture")


def read_capture(cfg: IngestConfig) -> tuple[CaptureSource, str]:
    """(source, how the format was chosen)."""
    from avatarctl.ingest.readers import reader_for
    from avatarctl.io.detect import detect_format
    from avatarctl.io.monocular import is_monocular_source, read_monocular

    if cfg.format == "video" or (cfg.format == "auto" and is_monocular_source(cfg.capture)):
        if not cfg.capture.exists():
            raise InputError("video not found", where=str(cfg.capture), fix="pass a video file or a folder of frames")
        reason = "given with --format" if cfg.format == "video" else \
            ("a video file" if cfg.capture.is_file() else "a folder of frames without calibration")
        return read_monocular(cfg.capture, cfg.focal_px, cfg.fov_deg), reason + ": one static camera"
    if cfg.focal_px is not None or cfg.fov_deg is not None:
        raise InputError("--focal-px / --fov-deg are for one video; this capture has its calibration",
                         where=str(cfg.capture), fix="drop the option (or pass a video file or a folder of frames)")
    if not cfg.capture.is_dir():
        raise InputError("capture folder not found", where=str(cfg.capture), fix="pass the folder of the capture")
    if cfg.format == "auto":
        fmt, reason = detect_format(cfg.capture)
    else:
        fmt, reason = cfg.format, "given with --format"
    return reader_for(fmt)(cfg.capture), reason


def select_views(src: CaptureSource, views: tuple[str, ...] | None) -> list[str]:
    names = src.camera_names
    if views is None:
        if src.uncalibrated:
            raise InputError(f"extra cameras: image folders {fmt_list(src.uncalibrated)} have no calibration",
                             where=str(src.root),
                             fix="calibrate them, or choose the calibrated cameras with --views")
        return names
    unknown = [v for v in views if v not in names]
    if unknown:
        raise InputError(f"--views names unknown cameras {unknown}", where=str(src.root),
                         fix=f"calibrated cameras are: {', '.join(names)}")
    return [n for n in names if n in set(views)]


# where each format keeps the body fits it ships (for the one-line error of a capture without them)
_FITS_AT = {"dna_rendering": "the annotations file's SMPLx group", "4d_dress": "SMPLX/ or SMPL/ pickles",
            "zju": "params/ or new_params/", "thuman4": "smpl_params.npz", "peoplesnapshot": "reconstructed_poses.hdf5"}


def _no_fits(fmt: str) -> str:
    return f"no body fits ({_FITS_AT.get(fmt, 'motion.npz or smpl/*.json')})"


def resolve_fits(cfg: IngestConfig, src: CaptureSource) -> str:
    from avatarctl.body.registry import needs_model_file

    """"files" (the capture's fits) or "keypoints" (estimated: MediaPipe keypoints -> a fit of `--body-model`, anny
    by default; smpl / smplx need `--body-model-path`)."""
    mode = cfg.fits if cfg.fits != "auto" else ("files" if src.fits is not None else "keypoints")
    if mode == "files" and src.fits is None:
        raise InputError(_no_fits(src.format), where=str(src.root),
                         fix="add motion.npz (avatarctl BodyMotion) or EasyMocap smpl/%06d.json fits, or estimate "
                             "them with --fits keypoints" if src.format not in _FITS_AT else
                             f"add the release's fits ({_FITS_AT[src.format]}), or estimate them with --fits keypoints")
    if mode == "keypoints":
        bm = cfg.body_model or "anny"
        if bm == "toy":
            raise InputError("--fits keypoints fits anny, smpl or smplx, not the toy body",
                             fix="use --body-model anny | smpl | smplx")
        if needs_model_file(bm) and cfg.body_model_path is None:
            raise InputError(f"--fits keypoints --body-model {bm} needs the {bm} model file",
                             fix=f"pass --body-model-path /path/to/{bm.upper()}_NEUTRAL.pkl (or .npz), or drop "
                                 "--body-model to fit anny")
        if needs_model_file(bm) and not cfg.body_model_path.is_file():
            raise InputError(f"{bm} model file not found", where=str(cfg.body_model_path),
                             fix="check --body-model-path")
        from avatarctl.ingest.keypoints import require_mediapipe

        require_mediapipe(f"{_no_fits(src.format) if src.fits is None else '--fits keypoints'}: estimating them",
                          "add motion.npz / smpl/%06d.json fits")
    return mode


def resolve_masks(cfg: IngestConfig, src: CaptureSource, cams: list[str], frames: list[int]) -> str:
    mode = cfg.masks
    if mode == "auto":  # MediaPipe's masks refined against the plates beat the plates' matting (docs/formats.md)
        from avatarctl.ingest.keypoints import mediapipe_installed

        mode = ("files" if src.masks is not None else
                "background" if all(c in src.backgrounds for c in cams) and not mediapipe_installed() else
                "mediapipe")
    if mode == "files":
        if src.masks is None or src.mask_frames is None:
            raise InputError("the capture has no mask files", where=str(src.root),
                             fix="add masks/<cam>/%06d.png, or use --masks background with background/<cam>.jpg, "
                                 "or --masks mediapipe")
        check_complete(src.mask_frames, cams, frames, "masks", src.root)
    elif mode == "background":
        missing = [c for c in cams if c not in src.backgrounds]
        if missing:
            raise InputError(f"no mask files and no background plate for cameras {fmt_list(missing)}",
                             where=str(src.root),
                             fix="add masks/<cam>/%06d.png or background/<cam>.jpg (an empty frame of each camera), "
                                 "or use --masks mediapipe")
    else:
        from avatarctl.ingest.keypoints import require_mediapipe

        why = "--masks mediapipe" if cfg.masks == "mediapipe" else "no mask files and no background plate: " \
                                                                    "estimating person masks"
        require_mediapipe(why, "add masks/<cam>/%06d.png or background/<cam>.jpg")
    return mode


@dataclass
class IngestPlan:
    """Everything decided and validated before a pixel is read (see `plan_ingest`)."""

    source: CaptureSource
    format_reason: str
    cams: list[str]  # selected camera names, capture order
    frames: list[int]  # selected capture frame numbers, ascending
    masks_mode: str  # "files" | "background" | "mediapipe"
    body_model: str  # "anny" | "smpl" | "smplx" | "toy"
    body: object  # the BodyModel (AnnyBody / SmplBody)
    motion: object  # BodyMotion, one row per selected frame (None until estimated, for fits "keypoints")
    faces: np.ndarray | None  # [F, 3] body mesh triangles (None until the fits are estimated)
    fits_mode: str = "files"  # "files" | "keypoints"
    detections: object = None  # `Detections` (with masks for masks "mediapipe") once the people are detected
    resize: float = 1.0  # scale after undistortion (--resize, or the benchmark protocol's)
    benchmark: BenchmarkPlan | None = None  # `--benchmark`: its split, frames and record (avatarctl.ingest.benchmark)


def plan_ingest(cfg: IngestConfig) -> IngestPlan:
    """Read the capture, select views / frames, validate everything, convert the fits. Writes nothing."""
    from avatarctl.body.registry import load_body_model, needs_model_file
    from avatarctl.ingest.fits import check_cameras_metric, check_fits, to_body_motion, with_hand_mean

    _check_project_dest(cfg)
    src, reason = read_capture(cfg)
    cams = select_views(src, cfg.views)
    if src.split is not None:
        check_split_views(src.split, src.camera_names, where=str(src.root / "split.json"))
    cam_by_name = {c.name: c for c in src.cameras}
    check_cameras_metric([cam_by_name[c] for c in cams], where=str(src.root))
    available = sorted(set().union(*[src.image_frames.get(c, set()) for c in cams]))
    if not available:
        raise InputError("the selected cameras have no images", where=str(src.root),
                         fix="check the capture layout (docs/formats.md)")
    bench = None
    if cfg.benchmark is not None:
        from avatarctl.evaluate.benchmarks import benchmark
        from avatarctl.ingest.benchmark import plan_benchmark

        bench = plan_benchmark(benchmark(cfg.benchmark), src, cams, available, cfg.frames, cfg.views is not None)
        frames, cams = bench.frames, bench.cams
    else:
        frames = select_frames(cfg.frames, available)
    check_complete(src.image_frames, cams, frames, "images", src.root)
    if src.format == "video":
        from avatarctl.ingest.estimate import MIN_VIDEO_FRAMES

        if len(frames) < MIN_VIDEO_FRAMES:
            raise InputError(f"video too short: {len(frames)} frames, an avatar needs at least {MIN_VIDEO_FRAMES} "
                             "(2/3 train, 1/3 held out)", where=str(src.root),
                             fix="film longer (a slow turn of ~10 s) or select more frames with --frames")
    elif cfg.height_m is not None:
        raise InputError("--height is for one video (the monocular fit's scale prior)", where=str(src.root),
                         fix="drop --height")
    fits_mode = resolve_fits(cfg, src)
    masks_mode = resolve_masks(cfg, src, cams, frames)
    if fits_mode == "keypoints":
        bm_name = cfg.body_model or "anny"
        body = load_body_model(bm_name, cfg.body_model_path if needs_model_file(bm_name) else None)
        return IngestPlan(src, reason, cams, frames, masks_mode, bm_name, body, None, None, fits_mode,
                          resize=bench.resize if bench else cfg.resize, benchmark=bench)

    fits_where = src.fits_where or str(src.root)
    check_fits(src.fits, frames, fits_where)
    bm_name = cfg.body_model or src.fits.body_model
    if src.fits.body_model != bm_name:
        to_body_motion(src.fits, bm_name, None)  # raises the one-line mismatch error
    if needs_model_file(bm_name) and cfg.body_model_path is None:
        raise InputError(f"the capture's fits need the {bm_name} body model file", where=fits_where,
                         fix=f"pass --body-model-path /path/to/{bm_name.upper()}_NEUTRAL.pkl (or .npz)")
    body = load_body_model(bm_name, cfg.body_model_path if needs_model_file(bm_name) else None)
    motion_all = to_body_motion(src.fits, bm_name, body)
    if src.hands_from_mean:
        motion_all = with_hand_mean(motion_all, getattr(getattr(body, "data", None), "hands_mean", None), fits_where)
    motion = motion_all.for_frames(frames)
    check_fits(motion, frames, fits_where)  # converted SMPL transl, anny root translation
    faces = body.template(motion.select([0])).faces.cpu().numpy()
    return IngestPlan(src, reason, cams, frames, masks_mode, bm_name, body, motion, faces, fits_mode,
                      resize=bench.resize if bench else cfg.resize, benchmark=bench)


def run_ingest(cfg: IngestConfig, progress: ProgressFn | None = None) -> IngestResult:
    """Build the project `cfg.project` from the capture `cfg.capture`. See the module docstring."""
    import torch

    from avatarctl.atomic import atomic_dir
    from avatarctl.body.registry import needs_model_file
    from avatarctl.ingest.contact_sheet import Tile, pick, write_contact_sheet
    from avatarctl.geometry.silhouette import fraction_inside
    from avatarctl.ingest.split import default_split, restrict_split
    from avatarctl.ingest.undistort import Undistorter
    from avatarctl.io.project_io import save_benchmark, save_camera_colour, save_cameras, save_split, write_frame, \
        write_mask
    from avatarctl.project import BodyModelRef, Project, SourceRef, hash_tree, now_iso, sha256_file

    t0 = time.perf_counter()
    started = now_iso()
    plan = plan_ingest(cfg)
    src = plan.source
    cam_by_name = {c.name: c for c in src.cameras}
    source_hash, n_files = (sha256_file(src.root), 1) if src.root.is_file() else hash_tree(src.root)
    und = {c: Undistorter.for_camera(cam_by_name[c], plan.resize) for c in plan.cams}
    estimate = None
    if plan.fits_mode == "keypoints" or plan.masks_mode == "mediapipe":
        plan, estimate = _estimate(cfg, plan, und, progress)
    cams, frames, motion = plan.cams, plan.frames, plan.motion
    plates = _undistorted_plates(src, und) if plan.masks_mode == "background" else {}
    given = plan.benchmark.split if plan.benchmark is not None else src.split
    split = restrict_split(given, frames, cams) if given is not None else default_split(frames, cams)
    sheet_cams, sheet_frames = pick(cams, 4), pick(frames, 6 if len(cams) == 1 else 3)
    tiles: list[Tile] = []
    inside: dict[str, list[float]] = {c: [] for c in cams}  # per camera, per frame
    shared = SharedColours(cams) if len(cams) >= 2 else None
    colour_frames = set(pick([f for f in split.train_frames if f in set(frames)], COLOUR_FRAMES))
    bm_path = str(cfg.body_model_path.resolve()) if cfg.body_model_path and needs_model_file(plan.body_model) else None

    with atomic_dir(cfg.project) as tmp:
        proj = Project.create(tmp.resolve(), body_model=BodyModelRef(name=plan.body_model, path=bm_path),
                              source=SourceRef(path=str(src.root.resolve()), format=src.format, sha256=source_hash,
                                               files=n_files))
        for s in range(0, len(frames), POSE_CHUNK):
            with torch.no_grad():
                verts = plan.body.pose(motion.select(slice(s, s + POSE_CHUNK))).vertices.cpu().numpy()  # [n, V, 3]
            for k, frame in enumerate(frames[s:s + POSE_CHUNK]):
                views: list[tuple[np.ndarray, np.ndarray]] = []
                for c in cams:
                    want_tile = cfg.contact_sheet and c in sheet_cams and frame in sheet_frames
                    rgb, mask, sil = _process_view(plan, und[c], plates.get(c), c, frame, verts[k], want_tile)
                    inside[c].append(fraction_inside(und[c].target, verts[k], mask))
                    write_frame(proj, c, frame, rgb)
                    write_mask(proj, c, frame, mask)
                    if want_tile:
                        tiles.append(Tile(c, frame, rgb, mask, sil, _detected_points(plan.detections, c, frame)))
                    if shared is not None and frame in colour_frames:
                        views.append((rgb, mask))
                if views:
                    shared.add([und[c].target for c in cams], [v[0] for v in views], [v[1] > 0 for v in views],
                               verts[k], plan.faces)
                if progress is not None:
                    progress(ProgressReport(done=s + k + 1, total=len(frames), part="frames"))

        cameras_out = [und[c].target for c in cams]
        save_cameras(proj.paths.cameras, cameras_out)
        motion.save(proj.paths.body)
        save_split(proj.paths.split, split)
        outputs = [proj.paths.cameras, proj.paths.body, proj.paths.split]
        gains = shared.solve(split.train_views) if shared is not None else None
        if gains is not None:
            save_camera_colour(proj.paths.camera_colour, gains)
            outputs.append(proj.paths.camera_colour)
        if plan.detections is not None:
            plan.detections.save(proj.paths.keypoints)
            outputs.append(proj.paths.keypoints)
        if plan.benchmark is not None:
            record = replace(plan.benchmark.record, frames=len(frames), train_views=split.train_views,
                             test_views=split.test_views)
            save_benchmark(proj.paths.benchmark, record)
            outputs.append(proj.paths.benchmark)
        if tiles:
            write_contact_sheet(proj.paths.ingest_contact_sheet, tiles, sheet_cams, sheet_frames)
            outputs.append(proj.paths.ingest_contact_sheet)
        outputs += [proj.paths.frame(c, f) for f in (frames[0], frames[-1]) for c in cams]
        camera_inside = {c: float(np.mean(v)) for c, v in inside.items() if v}
        mean_inside = float(np.mean([x for v in inside.values() for x in v])) if camera_inside else 0.0
        warnings = []
        if plan.benchmark is not None and record.partial:
            warnings.append(f"the project falls short of benchmark {record.name} ({'; '.join(record.partial)}): "
                            "its figures are not comparable with the published ones")
        if mean_inside < MIN_INSIDE:
            warnings.append(f"only {100 * mean_inside:.1f}% of the body mesh projects inside the masks: check the "
                            "calibration / fits alignment on ingest/contact_sheet.png")
        warnings += _cameras_off_the_body(camera_inside, plan.masks_mode)
        seconds = time.perf_counter() - t0
        w, h = cameras_out[0].width, cameras_out[0].height
        summary = {"format": src.format, "cameras": len(cams), "frames": len(frames), "resolution": f"{w}x{h}",
                   "body_model": plan.body_model, "masks": plan.masks_mode,
                   "vertices_inside_masks": round(mean_inside, 4),
                   "vertices_inside_masks_per_camera": {c: round(v, 4) for c, v in camera_inside.items()},
                   "seconds": round(seconds, 2),
                   "fits": plan.fits_mode}
        if estimate is not None:
            summary["estimate"] = estimate.to_json()
        if gains is not None:
            summary["camera_colour"] = {v: [round(float(g), 3) for g in gains.gain[i]] if gains.estimated[i] else None
                                        for i, v in enumerate(gains.views)}
        if plan.benchmark is not None:
            summary["benchmark"] = {"name": record.name, "partial": record.partial}
        if src.format == "video":
            K = cameras_out[0].K
            summary["camera"] = {"focal_px": round(float(K[0, 0]), 2), "intrinsics": src.notes[0],
                                 "world": "the camera's frame (OpenCV: +x right, +y down, +z forward; camera at the "
                                          "origin; up is -y for a level phone)"}
        config = cfg.to_json() | {"resolved": {"format": src.format, "body_model": plan.body_model,
                                               "masks": plan.masks_mode, "fits": plan.fits_mode,
                                               "frames": len(frames), "views": cams}}
        proj.record("ingest", config, outputs, started, summary)
    return IngestResult(project=cfg.project, format=src.format, format_reason=plan.format_reason, cameras=cams,
                        frames=frames, resolution=(w, h), body_model=plan.body_model, masks_source=plan.masks_mode,
                        seconds=seconds, vertices_inside_masks=mean_inside,
                        notes=list(src.notes) + (plan.benchmark.notes if plan.benchmark else []), warnings=warnings,
                        fits_source=plan.fits_mode, estimate=estimate, camera_colour=gains)


def _estimate(cfg: IngestConfig, plan: IngestPlan, und: dict, progress: ProgressFn | None
              ) -> tuple[IngestPlan, EstimateReport]:
    """Detect the person in every view; estimate body fits (fits "keypoints") and keep MediaPipe's masks (masks
    "mediapipe"). Returns the plan restricted to the frames that could be used (with the body mesh's faces once the
    fits exist), and the figures."""
    from dataclasses import replace

    from avatarctl.ingest.estimate import EstimateReport, detect_people, estimate_fits

    src, cams, frames = plan.source, plan.cams, plan.frames

    def read_view(c: str, f: int) -> np.ndarray:
        rgb = src.images.read(c, f)
        _check_size(rgb, und[c].source, src.images.where(c, f))
        return und[c].image(rgb)

    from avatarctl.body.fit_keypoints import OUTLINE_WEIGHT, SILHOUETTE_WEIGHT

    w_sil = SILHOUETTE_WEIGHT if cfg.keypoint_silhouette is None else cfg.keypoint_silhouette
    w_out = OUTLINE_WEIGHT if cfg.keypoint_outline is None else cfg.keypoint_outline
    silhouette = plan.fits_mode == "keypoints" and (w_sil > 0 or w_out > 0)
    # the silhouette term's masks: the capture's mask files, else MediaPipe's (also with background plates: the
    # plate matting needs the fitted body as its seed)
    det = detect_people(read_view, cams, frames, progress=progress,
                        masks=plan.masks_mode == "mediapipe" or (silhouette and plan.masks_mode == "background")
                        or src.format == "video", smooth=src.format == "video")
    refined = None
    if plan.masks_mode == "mediapipe" and cfg.refine_masks:  # static cameras: the capture's plates, else estimated
        from avatarctl.ingest.estimate import refine_masks

        det, refined = refine_masks(det, read_view, progress,
                                    plate_of=lambda c: _usable_plate(src, und, c))
    motion, kept = plan.motion, list(frames)
    if src.format == "video" and plan.fits_mode == "keypoints":
        from avatarctl.ingest.estimate import check_monocular, estimate_monocular

        usable = check_monocular(det, lambda f: read_view(cams[0], f), str(src.root))
        est = estimate_monocular(det, und[cams[0]].target, plan.body, cfg.keypoint_fit_iters, src.fps or 30.0,
                                 usable, cfg.height_m, progress,
                                 read_mask=(lambda c, f: det.mask(c, f)) if plan.masks_mode == "mediapipe" else None,
                                 silhouette_weight=cfg.keypoint_silhouette, outline_weight=cfg.keypoint_outline,
                                 offsets=cfg.keypoint_offsets)
        report, motion, kept = est.report, est.motion, est.kept
    elif plan.fits_mode == "keypoints":
        def read_mask(c: str, f: int) -> np.ndarray:
            if plan.masks_mode == "files":
                m = src.masks.read(c, f)
                _check_size(m, und[c].source, src.masks.where(c, f))
                return und[c].mask(m)
            return det.mask(c, f)

        est = estimate_fits(det, [und[c].target for c in cams], plan.body, cfg.keypoint_fit_iters, src.fps or 30.0,
                            progress, read_mask=read_mask if silhouette else None,
                            silhouette_weight=w_sil, outline_weight=w_out, offsets=cfg.keypoint_offsets)
        report, motion, kept = est.report, est.motion, est.kept
    else:
        found = det.found
        nan = float("nan")
        report = EstimateReport(frames_detected=int((found.sum(1) >= 2).sum()), frames_total=len(frames),
                                views_with_person=float(found.mean()), frames_skipped=[], mean_reprojection_px=nan,
                                views_rejected=nan, keypoints_triangulated=nan, fit_error_cm=nan, fit_seconds=0.0)
    if refined is not None:
        report = replace(report, masks_refined=refined)
    if det.enlarged:
        report = replace(report, detected_enlarged=det.enlarged)
    if plan.masks_mode == "mediapipe":
        no_mask = [f for f in kept if not det.mask_found(f)]
        kept = [f for f in kept if f not in set(no_mask)]
        report = replace(report, frames_skipped=sorted(set(report.frames_skipped) | set(no_mask)),
                         frames_no_mask=no_mask)
    if not kept:
        raise InputError(f"no usable frame: a person was found in 2+ views in {report.frames_detected} of "
                         f"{len(frames)} frames, {len(report.frames_no_mask)} of them lack a person mask in some view",
                         where=str(src.root), fix="check the images (the whole person, at least ~100 px tall, in view "
                                                  "of several cameras), or provide masks and fits")
    if len(kept) < len(frames):
        rows = [frames.index(f) for f in kept]
        if plan.fits_mode == "files":
            motion = motion.select(rows)
        elif len(kept) < motion.frame_index.shape[0]:
            motion = motion.select([i for i, f in enumerate(motion.frame_index) if int(f) in set(kept)])
    faces = plan.faces if plan.faces is not None else plan.body.template(motion.select([0])).faces.cpu().numpy()
    return replace(plan, frames=kept, motion=motion, detections=det, faces=faces), report


def _cameras_off_the_body(camera_inside: dict[str, float], masks_mode: str) -> list[str]:
    """One warning naming the cameras (of 3 or more) whose masks hold under `CAMERA_INSIDE` x the cameras' median
    share of the body mesh (`camera_inside`: camera -> mean share of vertices projecting inside its masks): their
    masks are not the person (MediaPipe latched onto something else; a wrong mask file), which costs the avatar (synth
    tight, one camera of four at 0.21 against 0.87-0.92: 1.4 dB against its true masks; leaving the camera out
    instead: level on held-out views, -0.3 dB on novel poses; docs/experiments/refined_masks_2026-11-30)."""
    if len(camera_inside) < 3:
        return []
    median = float(np.median(list(camera_inside.values())))
    bad = [c for c, v in camera_inside.items() if v < CAMERA_INSIDE * median]
    if not bad:
        return []
    shares = ", ".join(f"{c} {100 * camera_inside[c]:.0f}%" for c in bad)
    fix = "mask files from another segmenter (--masks files)" if masks_mode == "mediapipe" else "corrected mask files"
    return [f"the masks of camera(s) {shares} hold little of the body mesh (the cameras' median {100 * median:.0f}%): "
            f"they are not the person there; look at ingest/masks/<camera> and give {fix}"]


def _detected_points(det, cam: str, frame: int) -> np.ndarray | None:
    """[joints, 2] detected keypoints of one view (NaN: not found), or None when nothing was detected."""
    if det is None:
        return None
    return det.keypoints[det.frames.index(frame), det.cams.index(cam)]


def _undistorted_plates(src: CaptureSource, und: dict) -> dict[str, np.ndarray]:
    """camera -> undistorted (and resized) background plate, RGB uint8 [H, W, 3]; a plate that cannot be read or has
    another size than its camera's calibration is an `InputError`."""
    from avatarctl.io.capture import read_image_file

    plates = {}
    for c, u in und.items():
        plate = read_image_file(src.backgrounds[c], c, -1)
        _check_size(plate, u.source, str(src.backgrounds[c]))
        plates[c] = u.image(plate)
    return plates


def _usable_plate(src: CaptureSource, und: dict, cam: str) -> np.ndarray | None:
    """Camera `cam`'s plate as `_undistorted_plates` gives it, or None where it has none or it cannot be used (the
    masks' refinement then estimates that camera's plate from its frames)."""
    if cam not in src.backgrounds:
        return None
    try:
        return _undistorted_plates(src, {cam: und[cam]})[cam]
    except InputError:
        return None


def _process_view(plan: IngestPlan, u, plate: np.ndarray | None, cam: str, frame: int, verts: np.ndarray,
                  want_silhouette: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """One camera at one frame -> (undistorted RGB [H, W, 3], mask bool [H, W], body silhouette or None).

    `u` is the camera's `Undistorter`; `verts` [V, 3] the posed body (world); `plate` the undistorted background
    plate (background masks only)."""
    from avatarctl.ingest.masks import background_mask
    from avatarctl.geometry.silhouette import rasterize_silhouette

    src = plan.source
    rgb = src.images.read(cam, frame)
    _check_size(rgb, u.source, src.images.where(cam, frame))
    rgb = u.image(rgb)
    sil = None
    if plan.masks_mode == "background" or want_silhouette:
        sil = rasterize_silhouette(u.target, verts, plan.faces)
    if plan.masks_mode == "mediapipe":
        mask = plan.detections.mask(cam, frame)
        where, fix = src.images.where(cam, frame), "provide mask files or background plates"
    elif plan.masks_mode == "files":
        m = src.masks.read(cam, frame)
        _check_size(m, u.source, src.masks.where(cam, frame))
        mask = u.mask(m)
        where, fix = src.masks.where(cam, frame), "fix the mask (foreground > 0), or leave the frame out with --frames"
    else:
        mask = background_mask(rgb, plate, sil)
        where = f"{src.images.where(cam, frame)} vs {src.backgrounds[cam]}"
        fix = "check the background plate, or provide mask files"
    if not mask.any():
        raise InputError(f"empty mask: camera {cam}, frame {frame}", where=where, fix=fix)
    if mask.mean() > MAX_FOREGROUND:
        raise InputError(f"mask covers the whole image ({100 * mask.mean():.1f}% foreground; inverted?): camera "
                         f"{cam}, frame {frame}", where=where, fix=fix)
    return rgb, mask, sil


def _check_size(img: np.ndarray, cam, where: str) -> None:
    """`img` [H, W, ...] must have the calibrated size of `cam`."""
    if img.shape[:2] != (cam.height, cam.width):
        raise InputError(f"image is {img.shape[1]}x{img.shape[0]} but camera {cam.name} is calibrated for "
                         f"{cam.width}x{cam.height}", where=where,
                         fix="use the calibration that belongs to these images")
