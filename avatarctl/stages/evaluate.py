"""The eval stage (`avatarctl eval PROJECT`): render held-out images and score them against ground truth.

Splits (frames x views; `--frames` / `--views` / `--every` narrow them):
- `novel_view`: the avatar's training frames seen from the held-out (test) views; latent z = mu (paper Sec. 4.1);
- `novel_pose`: the project's test frames (poses never trained on) from the test views; latent z = 0;
- `train`: training frames from the training views; latent z = mu.

Ground truth: the ingested (undistorted) frame composited with its mask over the background colour the avatar was
trained with (`FitConfig.background`): gt = image * mask + background * (1 - mask)
(`evaluate.protocols.ground_truth`). The avatar is rendered over
the same colour, so pixels outside the person score only the avatar's stray density.

Protocols (`avatarctl.evaluate.protocols`): `bbox` (Neural Body / SLRF: PSNR over the projected 3D body box, SSIM on
its bounding rectangle; only that rectangle is rendered), `full` (every pixel) or `mpmavatar` (both images times the
eroded, blurred ground-truth mask, near-white pixels zeroed; every pixel; `mpmavatar_4d_dress`: without the cut).
Scores come only from `avatarctl.evaluate.metrics` (float32, settings and scikit-image version recorded). The
split's score is the mean over (frame, view) images of the per-image PSNR / SSIM (Neural Body's averaging).

Named benchmark protocols (`avatarctl.evaluate.benchmarks`; `benchmark`: "auto" = the one the project was ingested
with, `ingest --benchmark`, recorded in ingest/benchmark.json): the protocol's split, pixel protocol and background
replace `split` / `protocol` and the fit's background (the avatar is rendered, and the ground truth composited,
over the protocol's background; a fit trained over another one is named in one warning line); metrics.json records
the protocol's name, the published figures it is comparable with, and why it is not (a partial project). A
novel_view protocol scores its own test frames (those the avatar trained on; `--frames` narrows them). A protocol
whose test frames are another recording (`BenchmarkProtocol.test_sequence`, 4D-DRESS's other take) is scored with
`test_project`: the project ingested from that recording under the same protocol; its test frames (all novel poses,
whatever their numbers) from its test views, the avatar driven by its body fits with the avatar's own body shape,
against its images and masks (and its ground-truth geometry for `--region`).

Cameras that disagree in colour (issue 51): a training view is rendered as the avatar learned it: through its
camera's learned transform when the avatar was fitted with them (`model.colour.enabled`, model/colour.py), else in
the training cameras' mean colour (identity). A camera the avatar never trained on (a held-out view) is rendered
through its gains relative to the training cameras' mean that ingest estimated from the body's colours across
cameras (ingest/camera_colour.json, `evaluate.colour.SharedColours`: the capture's images and fits, no render),
named in metrics.json "camera_colour" and the printed table; `camera_colour="off"` (`--camera-colour off`), or a
project without the file, renders it in the training cameras' mean colour. Beside the plain figure, every image is also scored
NeRF-W's way, clearly apart (metrics.json "colour_matched", `evaluate.report.ColourMatched`, its own row in the
printed table): the camera's transform (3 gains + 3 offsets on the foreground, `evaluate.colour`) estimated by least
squares on the LEFT half of the protocol's region (where render and mask both hold the subject), the render through it
scored on the RIGHT half, with the plain render's PSNR on the same right halves to compare with.

The held-out frames' poses (`novel_pose`): ingest's body fits, or, where the fit posed those frames with the avatar's
silhouette against the training views' masks (fit/held_out_poses.py; estimated fits), the fit's poses, when its
`fit/held_out_poses.npz` was written for the checkpoint scored (another checkpoint's: a warning, ingest's poses).
metrics.json "held_out_poses" and a table row say so; `held_out_poses = "ingest"` (`--held-out-poses ingest`) scores
ingest's poses. The scored pixels (the bbox region) come from ingest's fits either way.

Held-out poses scored fairly (issue 51; `refine_pose` > 0, `--refine-pose STEPS`): beside the plain figure, each
frame is also scored after its body pose (the one the plain figure drives it with) is refined against that frame's
scored images with the avatar frozen (`fit.frame_pose`, `REFINED_PROTOCOL`: the monocular papers' protocol, whose
estimated test poses are off by a limb's width), on the same pixels: metrics.json "refined_pose"
(`evaluate.report.RefinedPose`), per_frame.csv refined_psnr / refined_ssim, its own table row and `sheet_refined.png`.
Only the Gaussian local fields. With
`refine_pose_from = "masks"` (`--refine-pose-from masks`) each pose is fitted to the frame's masks alone, the avatar's
silhouette against them, its colours unused; metrics.json says which ("target").

LPIPS is reported only when the `lpips` package and its AlexNet weights are already on this machine (nothing is
downloaded); otherwise `"lpips": null` with the reason.

Several ranks (`nproc`, or a torchrun launch; `stages.common.run_ranked`): rank r scores the frames r, r + N, ...
(every view of a frame on one rank; `--save-images` PNGs go into rank 0's temporary directory), rank 0 gathers the
scores in the single-process order and writes the report: the same numbers as one process.

Writes `eval/<name>/metrics.json`, `per_frame.csv`, `sheet.png` and, with `--save-images`,
`renders/<frame:06d>_<view>.png` atomically (all or nothing), and records the stage. What is saved is typed in
`avatarctl.evaluate.report` (`EvalMetrics`, `ImageScore`).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from avatarctl.errors import InputError
from avatarctl.evaluate.report import PSNR_CAP, SCHEMA_VERSION, EvalMetrics, ImageScore, ScoredModel
from avatarctl.frames import select_frames
from avatarctl.project import Project, check_name, now_iso
from avatarctl.progress import ProgressReport, ProgressFn
from avatarctl.stages.common import check_knockout, check_latent_mode, frame_conditioning, frame_node_state, \
    knocked_out, latent_for, load_fitted, open_fitted, rank_device_name, run_ranked, select_views, writing

SPLITS = ("novel_view", "novel_pose", "train")
HELD_OUT_POSES = ("fit", "ingest")  # `held_out_poses`: whose poses drive the held-out frames (module docstring)
_REFINED = ("per frame, the body pose (rotations of the joints that carry >= model.pose_refine.min_share of the "
            "skinning weight, about their centres, and the root translation; model/pose_refine.py) optimised against "
            "that frame's scored {what} with the avatar frozen (fit/frame_pose.py: Adam, {loss} over the protocol's "
            "crops, the first half of the steps at half resolution), then rendered and scored on the same pixels as "
            "the plain figure")
REFINED_PROTOCOL = {  # by `refine_pose_from`
    "images": "InstantAvatar / GART test-time pose: " + _REFINED.format(
        what="images", loss="the fit's L1 + D-SSIM + mask loss"),
    "masks": "pose from the masks: " + _REFINED.format(
        what="views' masks (not their colours)", loss="mean |alpha - mask|, the avatar's silhouette against the mask"),
}
MATCHED_PROTOCOL = ("NeRF-W: per image, the camera's colour gains (per channel, on the rendered foreground: the "
                    "ratio of the summed colours, evaluate.colour.estimate_colour) from the left half of the "
                    "protocol's region (split at the middle column of its bounding rectangle), on the pixels that are "
                    "foreground in both the render (alpha >= 0.5) and the mask; the render through them scored on the "
                    "whole right half; plain_psnr: the render as it is on the same right halves")


@dataclass(frozen=True)
class EvalConfig:
    """What `avatarctl eval` scores. Saved in metrics.json and the manifest."""

    split: str = "novel_view"  # novel_view | novel_pose | train
    protocol: str = "bbox"  # bbox | full
    name: str | None = None  # eval/<name>; None = "<split>_<protocol>"
    frames: str | None = None  # frame selection within the split (see avatarctl.frames)
    views: tuple[str, ...] = ()  # cameras; () = the split's views
    every: int = 1  # keep every N-th selected frame (Neural Body tests every 30th)
    latent: str = "auto"  # auto = mean for training frames, zero for novel; or mean | zero | sample
    seed: int = 0  # for latent "sample"
    sheet_rows: int = 4  # (frame, view) pairs shown in sheet.png
    bbox_pad: float = 0.05  # metres the posed body box is grown by (Neural Body: 0.05)
    max_rays_per_chunk: int = 8192
    device: str = "auto"  # auto | cpu | cuda
    checkpoint: str | None = None  # None = fit/checkpoints/latest.pt
    save_images: bool = False  # also write every render to eval/<name>/renders/<frame:06d>_<view>.png
    region: str = "all"  # what the headline PSNR is over: all (the protocol's region) | garment | body | edge | inner
    knockout: tuple[str, ...] = ()  # render-time knockout of a trained model: delta-n and/or embedding (Fig. 3)
    benchmark: str = "auto"  # auto (the project's ingest --benchmark, if any) | none | a protocol name
    test_project: str | None = None  # the project of the protocol's test recording (`--test-project`), if any
    camera_colour: str = "auto"  # auto: held-out cameras through ingest's gains (module docstring) | off
    refine_pose: int = 0  # > 0: also score each frame after refining its body pose for this many steps (docstring)
    refine_pose_from: str = "images"  # what the pose is refined against: images (colours + masks) | masks (alone)
    held_out_poses: str = "fit"  # held-out frames' poses: fit (the fit's, where it posed them) | ingest (as ingested)

    def __post_init__(self) -> None:
        from avatarctl.evaluate.protocols import PROTOCOLS

        object.__setattr__(self, "views", tuple(self.views))
        object.__setattr__(self, "knockout", check_knockout(tuple(self.knockout)))
        if self.split not in SPLITS:
            raise InputError(f"unknown split {self.split!r}", where="--split", fix=f"use one of: {', '.join(SPLITS)}")
        if self.protocol not in PROTOCOLS:
            raise InputError(f"unknown protocol {self.protocol!r}", where="--protocol",
                             fix=f"use one of: {', '.join(PROTOCOLS)}")
        check_latent_mode(self.latent)
        from avatarctl.evaluate.regions import REGIONS

        if self.region not in REGIONS:
            raise InputError(f"unknown region {self.region!r}", where="--region", fix=f"use one of: {', '.join(REGIONS)}")
        if self.every < 1:
            raise InputError(f"--every must be >= 1, got {self.every}", where="--every", fix="e.g. --every 30")
        if self.camera_colour not in ("auto", "off"):
            raise InputError(f"unknown camera colour {self.camera_colour!r}", where="--camera-colour",
                             fix="use auto or off")
        if self.refine_pose < 0:
            raise InputError(f"--refine-pose must be >= 0 steps, got {self.refine_pose}", where="--refine-pose",
                             fix="e.g. --refine-pose 40 (0: off)")
        from avatarctl.fit.frame_pose import POSE_TARGETS

        if self.held_out_poses not in HELD_OUT_POSES:
            raise InputError(f"unknown --held-out-poses {self.held_out_poses!r}", where="--held-out-poses",
                             fix=f"use one of: {', '.join(HELD_OUT_POSES)}")
        if self.refine_pose_from not in POSE_TARGETS:
            raise InputError(f"unknown --refine-pose-from {self.refine_pose_from!r}", where="--refine-pose-from",
                             fix=f"use one of: {', '.join(POSE_TARGETS)}")
        if self.refine_pose and self.latent == "sample":
            raise InputError("--refine-pose needs a deterministic latent", where="--latent",
                             fix="drop --latent sample (or --refine-pose)")
        if self.sheet_rows < 0:
            raise InputError(f"--sheet must be >= 0, got {self.sheet_rows}", where="--sheet", fix="e.g. --sheet 4")
        if not 0.0 <= self.bbox_pad <= 1.0:
            raise InputError(f"bbox pad {self.bbox_pad} m outside [0, 1]", fix="e.g. 0.05")
        if self.benchmark not in ("auto", "none"):
            from avatarctl.evaluate.benchmarks import benchmark

            benchmark(self.benchmark)
        check_name(self.out_name, "eval name")

    @property
    def out_name(self) -> str:
        return self.name or f"{self.split}_{self.protocol}"

    def to_json(self) -> dict[str, Any]:
        d = asdict(self)
        d["views"] = list(self.views)
        d["knockout"] = list(self.knockout)
        d["name"] = self.out_name
        return {"schema_version": SCHEMA_VERSION, **d}


@dataclass
class EvalResult:
    out_dir: Path
    metrics: EvalMetrics  # what metrics.json holds
    seconds: float  # whole stage
    scores: list[ImageScore] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)  # one line each (a fit background the protocol overrides)

    @property
    def psnr(self) -> float:
        return float(self.metrics.psnr)

    @property
    def ssim(self) -> float:
        return float(self.metrics.ssim)


def split_pairs(avatar: Any, cfg: EvalConfig, scored: Any = None, proto: Any = None
                ) -> tuple[list[int], list[str], bool]:
    """(frames, views, frames_are_training) for the split, after --frames / --views / --every. `scored`: the test
    project's capture (`test_project`: its test frames and views, none a training frame); `proto`: the benchmark
    protocol (novel_view: only its test frames)."""
    cap = scored if scored is not None else avatar.capture
    split = cap.split
    trained = sorted(set(int(f) for f in avatar.train_frames))
    if scored is not None:
        pool, is_train, views = sorted(set(int(f) for f in split.test_frames)), False, list(split.test_views)
    elif cfg.split in ("novel_view", "train"):
        pool, is_train = trained, True
        if proto is not None and cfg.split == "novel_view":
            pool = sorted(set(pool) & set(proto.test_frame_numbers()))
        views = list(split.test_views if cfg.split == "novel_view" else split.train_views)
    else:
        pool = sorted(set(int(f) for f in split.test_frames) - set(trained))
        is_train = False
        views = list(split.test_views)
    if not pool:
        raise InputError(f"the project has no frames for split {cfg.split}", where=str(cap.project.root),
                         fix="choose another --split" if cfg.split == "novel_pose" else "re-run `avatarctl fit`")
    frames = select_frames(cfg.frames, pool, what="--frames")[::cfg.every]
    if cfg.views:
        views = select_views(cfg.views, cap.cameras)
    if not views:
        raise InputError(f"the project's split has no views for {cfg.split}", where=str(cap.project.paths.split),
                         fix="pass --views CAM1,CAM2")
    return frames, views, is_train


def resolve_benchmark(project: Project, cfg: EvalConfig) -> tuple[EvalConfig, Any, Any]:
    """(cfg, protocol, ingested record): `cfg` with the named benchmark protocol's split and pixel protocol and its
    `benchmark` made concrete (a name, or "none"); protocol and record None without one. A name the project was not
    ingested with is refused (its split is not the protocol's)."""
    from dataclasses import replace

    from avatarctl.evaluate.benchmarks import benchmark
    from avatarctl.io.project_io import load_benchmark

    record = load_benchmark(project) if cfg.benchmark != "none" else None
    if record is None and cfg.benchmark in ("auto", "none"):
        _check_test_project(project, cfg, None, None)
        return replace(cfg, benchmark="none"), None, None
    if record is None:
        raise InputError(f"the project was not ingested with --benchmark {cfg.benchmark}", where=str(project.root),
                         fix=f"ingest the capture again with --benchmark {cfg.benchmark} (its split is the "
                             "protocol's), or drop --benchmark")
    if cfg.benchmark not in ("auto", record.name):
        raise InputError(f"the project was ingested with --benchmark {record.name}, not {cfg.benchmark}",
                         where=str(project.paths.benchmark), fix=f"use --benchmark {record.name}, or drop it")
    proto = benchmark(record.name)
    _check_test_project(project, cfg, proto, record)
    return replace(cfg, split=proto.split, protocol=proto.pixels, benchmark=proto.name), proto, record


def _check_test_project(project: Project, cfg: EvalConfig, proto: Any, record: Any) -> None:
    """Refuse, in one line, a `cfg.test_project` that is not the test recording of the project's protocol `proto`
    (`record`: the project's `IngestedBenchmark`), and a two-recording protocol without one."""
    from avatarctl.io.project_io import load_benchmark

    two = proto is not None and proto.test_sequence is not None
    if cfg.test_project is None:
        if two:
            raise InputError(f"benchmark {proto.name} scores another recording ({proto.test_sequence})",
                             where=str(project.root), fix=f"ingest it with --benchmark {proto.name} and pass its "
                             "project as --test-project (or --benchmark none to score this one)")
        return
    if not two:
        raise InputError(f"--test-project is for a benchmark whose test frames are another recording; "
                         f"{'this project has no benchmark' if proto is None else proto.name + ' is not one'}",
                         where="--test-project", fix="drop --test-project")
    if record.role != "train":
        raise InputError(f"the project is the test recording ({record.sequence}) of benchmark {proto.name}",
                         where=str(project.root), fix=f"evaluate the project of {proto.sequence} with "
                         f"--test-project {project.root}")
    test = load_benchmark(Project.open(cfg.test_project))
    if test is None or test.name != proto.name:
        raise InputError(f"--test-project was ingested with {'no benchmark' if test is None else test.name}, not "
                         f"{proto.name}", where=str(cfg.test_project),
                         fix=f"ingest {proto.test_sequence} with --benchmark {proto.name}")
    if test.role != "test":
        raise InputError(f"--test-project is {test.sequence or 'a recording'}, not the test recording "
                         f"{proto.test_sequence} of benchmark {proto.name}", where=str(cfg.test_project),
                         fix=f"ingest {proto.test_sequence} with --benchmark {proto.name} and pass that project")


def run(project_dir: str | Path, cfg: EvalConfig, progress: ProgressFn | None = None, *,
        nproc: int = 1, wait: bool = False) -> EvalResult | None:
    """Run the eval stage on `project_dir` (see the module docstring) on `nproc` ranks (None on the ranks > 0 of
    a torchrun launch). Holds the lock of `eval/<name>`; `wait`: for another command writing it to finish, instead
    of refusing (`BusyError`)."""
    project = Project.open(project_dir)
    cfg = resolve_benchmark(project, cfg)[0]
    out_dir = project.paths.eval(cfg.out_name)
    with writing(out_dir, f"eval --name {cfg.out_name}", wait, sweep=True):
        return run_ranked(_run, nproc, (str(project_dir), cfg), progress, cfg.device, "eval")


@dataclass
class _Scored:
    """One scored (frame, view) image as a rank hands it to rank 0."""

    index: int  # position in the single-process order (frames outer, views inner)
    score: ImageScore
    lpips: float | None
    sheet: Any  # evaluate.sheet.SheetRow when the image is on the sheet, else None
    refined_sheet: Any = None  # its row after test-time pose refinement (`refine_pose`), else None
    refine_seconds: float = 0.0  # the pose refinement of its frame (counted on the frame's first view)


def _run(env: Any, progress: ProgressFn | None, project_dir: str, cfg: EvalConfig) -> EvalResult | None:
    import contextlib

    import torch

    from avatarctl.atomic import atomic_dir, write_json, write_text
    from avatarctl.dist import active, broadcast_from_main, gather_to_main
    from avatarctl.evaluate.metrics import lpips_status, metric_settings, psnr_from_mse
    from avatarctl.evaluate.protocols import GROUND_TRUTH
    from avatarctl.evaluate.regions import SILHOUETTE_REGIONS
    from avatarctl.evaluate.report import colour_matched, per_frame_csv, refined_pose, region_scores
    from avatarctl.evaluate.sheet import comparison_sheet
    from avatarctl.io.project_io import load_benchmark

    started = now_iso()
    t_start = time.perf_counter()
    project = open_fitted(project_dir, cfg.checkpoint, cfg.views)
    cfg, proto, bench = resolve_benchmark(project, cfg)
    avatar = load_fitted(project, rank_device_name(env, cfg.device), cfg.checkpoint)
    scored = _test_capture(avatar, cfg.test_project) if cfg.test_project is not None else None
    cap = scored if scored is not None else avatar.capture
    frames, views, is_train = split_pairs(avatar, cfg, scored, proto)
    if cfg.refine_pose and not avatar.model.field_kind.splats:
        raise InputError(f"--refine-pose renders whole crops: it needs the Gaussian local fields, this avatar's are "
                         f"{avatar.model.cfg.field!r}", where=str(project.root), fix="drop --refine-pose, or fit "
                         "with --preset cpu (model.field=gaussians)")
    latent = latent_for(cfg.latent, is_train)
    background = tuple(float(c) for c in (proto.background if proto is not None else avatar.background))
    warnings = []
    if proto is not None and tuple(float(c) for c in avatar.background) != background:
        warnings.append(f"the avatar was fitted over background {_rgb(avatar.background)}; benchmark {proto.name} "
                        f"renders and composites over {_rgb(background)}: scored over {_rgb(background)}")
    lpips_fn, lpips_reason = lpips_status()
    geometry = None if cfg.region in SILHOUETTE_REGIONS else _gt_geometry(cap.project, cfg.region)
    cams = {v: cap.cameras[v].pinhole() for v in views}
    gains = _held_out_gains(avatar, cap, cfg, views)
    held, note = _held_out_poses(project, avatar, cfg, is_train, scored)
    if note is not None:
        warnings.append(note)
    total = len(frames) * len(views)
    sheet_at = set(np.linspace(0, total - 1, min(cfg.sheet_rows, total)).round().astype(int).tolist()) \
        if cfg.sheet_rows else set()
    out_dir = project.paths.eval(cfg.out_name)
    world = env.world_size if active(env) else 1
    main = env is None or env.is_main
    with atomic_dir(out_dir) if main else contextlib.nullcontext() as tmp:  # all or nothing
        if main and cfg.save_images:
            (tmp / "renders").mkdir()
        tmp = broadcast_from_main(tmp, env)
        mine: list[_Scored] = []
        t0 = time.perf_counter()
        motion = cap.motion.for_frames(frames)
        for fi in range(env.rank if world > 1 else 0, len(frames), world):
            frame, one = frames[fi], motion.select([fi])
            verts = avatar.body.pose(one).vertices[0].detach().float().cpu().numpy()  # [V, 3]
            state = knocked_out(avatar, frame_node_state(avatar, one, frame, is_train, latent, cfg.seed, held),
                                cfg.knockout)
            refined = _refined_state(avatar, cap, cfg, frame_conditioning(avatar, one, frame, is_train, held), frame,
                                     latent, views, cams, verts, background, gains) if cfg.refine_pose else None
            for vi, view in enumerate(views):
                k = fi * len(views) + vi
                mine.append(_score_image(avatar, cap, cfg, project, state, verts, frame, view, cams[view], latent,
                                         lpips_fn, geometry, k in sheet_at, tmp, k, background, gains.get(view)))
                if refined is not None:
                    mine[-1] = _with_refined(mine[-1], refined[1], _score_image(
                        avatar, cap, replace(cfg, save_images=False), project, refined[0], verts, frame, view,
                        cams[view], latent, None, None, k in sheet_at, tmp, k, background, gains.get(view)), vi == 0)
                if progress is not None:
                    progress(ProgressReport(stage="eval", done=min(len(mine) * world, total), total=total,
                                            seconds=time.perf_counter() - t0, detail=mine[-1].score))
        gathered = gather_to_main(mine, env)
        if not main:
            return None
        done = sorted((s for part in gathered for s in part), key=lambda s: s.index)
        scores = [s.score for s in done]
        lpips_values = [s.lpips for s in done if s.lpips is not None]
        sheet_rows = [s.sheet for s in done if s.sheet is not None]
        refined_rows = [s.refined_sheet for s in done if s.refined_sheet is not None]

        regions = region_scores(scores)
        matched = colour_matched(scores, MATCHED_PROTOCOL)
        refined_fig = refined_pose(scores, cfg.refine_pose, sum(s.refine_seconds for s in done),
                                   REFINED_PROTOCOL[cfg.refine_pose_from], cfg.refine_pose_from)
        if cfg.region == "all":
            psnrs = np.minimum(np.array([s.psnr for s in scores], np.float64), PSNR_CAP)  # exact match: inf -> cap
        else:  # images where the region is empty are not scored
            psnrs = np.minimum(np.array([psnr_from_mse(s.region_mse[cfg.region]) for s in scores
                                         if s.region_pixels[cfg.region] > 0], np.float64), PSNR_CAP)
        ssims = np.array([s.ssim for s in scores], np.float64)
        render_seconds = float(sum(s.seconds for s in scores))
        mc = avatar.model_config
        metrics = EvalMetrics(
            schema_version=SCHEMA_VERSION,
            split=cfg.split,
            protocol=cfg.protocol,
            psnr=_finite_mean(psnrs),
            ssim=_finite_mean(ssims),
            lpips=float(np.mean(lpips_values)) if lpips_values else None,
            lpips_reason=lpips_reason,
            psnr_std=float(psnrs.std()) if len(psnrs) else None,
            psnr_min=float(psnrs.min()) if len(psnrs) else None,
            psnr_max=float(psnrs.max()) if len(psnrs) else None,
            ssim_std=float(ssims.std()) if len(ssims) else None,
            images=len(scores),
            frames=frames,
            views=views,
            every=cfg.every,
            averaging="mean over (frame, view) images of per-image PSNR / SSIM",
            checkpoint_step=avatar.step,
            checkpoint=str(avatar.checkpoint) if avatar.checkpoint else None,
            background=list(background),
            ground_truth=GROUND_TRUTH,
            latent=latent,
            protocol_details=_protocol_details(cfg),
            metric_settings=metric_settings(),
            model=ScoredModel(variant=mc.variant, latent=mc.latent, use_delta_n=mc.use_delta_n,
                              use_embedding=mc.use_embedding, ablations=list(avatar.fit_config.ablations)),
            image_size=[int(cams[views[0]].width), int(cams[views[0]].height)],
            timing={"render_seconds": round(render_seconds, 3),
                    "seconds_per_image": round(render_seconds / max(len(scores), 1), 4),
                    "device": str(avatar.device), "torch_threads": torch.get_num_threads()},
            config=cfg.to_json(),
            created=now_iso(),
            region=cfg.region,
            regions={k: asdict(v) for k, v in regions.items()} if regions else None,
            benchmark=proto.name if proto is not None else None,
            comparable_with=list(proto.comparable_with) if proto is not None else None,
            not_comparable=_not_comparable(cfg, bench, frames, views,
                                           load_benchmark(cap.project) if scored is not None else None),
            test_project=str(cap.project.root) if scored is not None else None,
            colour_matched=asdict(matched) if matched is not None else None,
            refined_pose=asdict(refined_fig) if refined_fig is not None else None,
            held_out_poses=_held_out_record(held, frames),
            camera_colour={"source": "ingest/camera_colour.json", "method": cap.camera_colour.method,
                           "gain": {v: [round(float(x), 4) for x in g] for v, g in gains.items()}} if gains else None,
        )
        write_json(tmp / "metrics.json", metrics.to_json())
        write_text(tmp / "per_frame.csv", per_frame_csv(scores))
        if sheet_rows:
            comparison_sheet(sheet_rows, tmp / "sheet.png",
                             title=f"{cfg.split} / {cfg.protocol}  step {avatar.step}  PSNR"
                                   + ("" if cfg.region == "all" else f" ({cfg.region})")
                                   + f" {metrics.psnr:.2f} dB  SSIM {metrics.ssim:.4f}")
            if refined_rows:
                comparison_sheet(refined_rows, tmp / "sheet_refined.png",
                                 title=f"{cfg.split} / {cfg.protocol}  step {avatar.step}  after test-time pose "
                                       f"refinement against the {cfg.refine_pose_from} ({cfg.refine_pose} steps)  "
                                       f"PSNR {refined_fig.psnr:.2f} dB  "
                                       f"SSIM {refined_fig.ssim:.4f}")
    seconds = round(time.perf_counter() - t_start, 3)
    project.record("eval", config=cfg.to_json(), outputs=[out_dir], started=started,
                   summary={"name": cfg.out_name, "split": cfg.split, "protocol": cfg.protocol,
                            "psnr": round(metrics.psnr, 3), "ssim": round(metrics.ssim, 4),
                            "images": len(scores), "checkpoint_step": avatar.step})
    return EvalResult(out_dir=out_dir, metrics=metrics, seconds=seconds, scores=scores, warnings=warnings)


def _rgb(c: Any) -> str:
    return ",".join(f"{float(x):g}" for x in c)


def _not_comparable(cfg: EvalConfig, bench: Any, frames: list[int], views: list[str], test_bench: Any = None
                    ) -> list[str] | None:
    """Why a benchmark figure is not the published protocol's (None without a benchmark (`bench`, the project's
    `IngestedBenchmark`; `test_bench`, the test project's); [] when it is)."""
    if bench is None:
        return None
    out = list(bench.partial) + [f"test project: {p}" for p in (test_bench.partial if test_bench else ())]
    if cfg.frames is not None or cfg.every != 1:
        out.append(f"eval frames narrowed (--frames {cfg.frames or 'all'}, --every {cfg.every}): {len(frames)} frames")
    if cfg.views:
        out.append(f"eval views narrowed to {', '.join(views)}")
    if cfg.region != "all" or cfg.knockout:
        out.append("a region or knockout score, not the protocol's")
    return out


def _score_image(avatar: Any, cap: Any, cfg: EvalConfig, project: Project, state: Any, verts: np.ndarray,
                 frame: int, view: str, cam: Any, latent: str, lpips_fn: Any, geometry: Any, on_sheet: bool, tmp: Path,
                 index: int, background: tuple[float, float, float], gain: np.ndarray | None) -> _Scored:
    """Render one (frame, view) over `background` and the protocol's region and score it against the ground truth
    of `cap` (the avatar's capture, or the test project's); `gain` [3]: the held-out camera's colour gains
    (`_held_out_gains`)."""
    from avatarctl.evaluate.metrics import mse_channels, psnr_from_mse, ssim
    from avatarctl.evaluate.protocols import bbox_region, full_region, ground_truth, mpmavatar_images
    from avatarctl.evaluate.regions import SILHOUETTE_REGIONS, silhouette_band, split_silhouette
    from avatarctl.evaluate.sheet import SheetRow
    from avatarctl.render.engine import render_view
    from avatarctl.render.images import write_png

    region = bbox_region(cam, verts, pad=cfg.bbox_pad) if cfg.protocol == "bbox" \
        else full_region(cam.height, cam.width)
    if not region.mask.any():
        raise InputError(f"the body box of frame {frame} is outside camera {view}", where=str(project.root),
                         fix="check the body fits / cameras (`avatarctl info`), or use --protocol full")
    x0, y0, x1, y1 = region.crop
    render_mask = None
    if cfg.protocol == "bbox":
        render_mask = np.zeros((cam.height, cam.width), bool)
        render_mask[y0:y1, x0:x1] = True
    view_out = render_view(avatar.model, state, 0, cam, background, max_rays_per_chunk=cfg.max_rays_per_chunk,
                           pixel_mask=render_mask)
    rgb = seen = _as_camera_sees(avatar, view, view_out.rgb, view_out.alpha, gain)  # [H, W, 3] as the camera sees it
    mask = cap.mask(view, frame)
    gt = ground_truth(cap.image(view, frame), mask, background)  # [H, W, 3]
    if cfg.protocol in ("mpmavatar", "mpmavatar_4d_dress"):
        rgb, gt = mpmavatar_images(rgb, gt, mask, white_cut=cfg.protocol == "mpmavatar")
    channel_mse = mse_channels(rgb, gt, region.mask)  # [3]
    e = float(channel_mse.mean())
    pred_crop, gt_crop = region.crop_image(rgb), region.crop_image(gt)
    try:
        s = ssim(pred_crop, gt_crop)
    except ValueError as err:
        raise InputError(f"cannot score frame {frame} view {view}: {err}", where=str(project.root),
                         fix="use --protocol full or a higher-resolution capture") from None
    region_mse = region_pixels = None
    if cfg.region in SILHOUETTE_REGIONS:
        region_mse, region_pixels = _part_errors(rgb, gt, split_silhouette(region.mask, silhouette_band(mask)),
                                                 SILHOUETTE_REGIONS)
    elif geometry is not None:
        region_mse, region_pixels = _garment_errors(rgb, gt, region.mask, cam, geometry, frame)
    score = ImageScore(frame=frame, view=view, psnr=psnr_from_mse(e), ssim=s, mse=e,
                       mse_rgb=tuple(float(x) for x in channel_mse),
                       pixels=int(region.mask.sum()),
                       latent=latent, seconds=round(view_out.seconds, 4), region_mse=region_mse,
                       region_pixels=region_pixels,
                       matched=_matched_score(rgb, view_out.alpha, gt, mask, background, region.mask, region.crop))
    if cfg.save_images:  # the full image; outside the bbox crop it is the background (not rendered)
        write_png(tmp / "renders" / f"{frame:06d}_{view}.png", seen, None)  # before the protocol's pixel rule
    sheet = SheetRow(gt=gt_crop, render=pred_crop, region=region.crop_image(region.mask),
                     label=f"frame {frame}  view {view}  latent {latent}  PSNR {score.psnr:.2f} dB  "
                           f"SSIM {score.ssim:.4f}") if on_sheet else None
    return _Scored(index=index, score=score, lpips=lpips_fn(pred_crop, gt_crop) if lpips_fn is not None else None,
                   sheet=sheet)


def _refined_state(avatar: Any, cap: Any, cfg: EvalConfig, cond: Any, frame: int, latent: str, views: list[str],
                   cams: dict[str, Any], verts: np.ndarray, background: tuple[float, float, float],
                   gains: dict[str, np.ndarray]) -> tuple[Any, Any]:
    """(node state, `fit.frame_pose.FramePose`) of `frame` (`cond`: its conditioning, the pose it starts from) after
    its body pose is refined against its images in `views` (module docstring), each over the protocol's box crop (the
    whole image for the other protocols)."""
    import torch

    from avatarctl.fit.frame_pose import FramePoseConfig, crop_views, refine_frame_pose, refined_state

    model = avatar.model
    colours = {v: _camera_colour(avatar, v, gains.get(v)) for v in views}
    pose_views = crop_views(cap, frame, views, cams, verts, background, avatar.device, pad=cfg.bbox_pad,
                            protocol="bbox" if cfg.protocol == "bbox" else "full", colours=colours)
    pose = refine_frame_pose(model, avatar.template, cond, pose_views, torch.tensor(background, dtype=torch.float32),
                             latent, FramePoseConfig(steps=cfg.refine_pose, target=cfg.refine_pose_from))
    return knocked_out(avatar, refined_state(model, cond, pose, latent), cfg.knockout), pose


def _with_refined(plain: "_Scored", pose: Any, again: "_Scored", first_view: bool) -> "_Scored":
    """`plain` with the score of the same image after its frame's pose refinement `pose` (`again`: rendered from the
    refined pose); the refinement's time is counted on the frame's first view."""
    from avatarctl.evaluate.report import RefinedScore

    score = replace(plain.score, refined=RefinedScore(psnr=again.score.psnr, ssim=again.score.ssim,
                                                      mse=again.score.mse, shift_cm=round(pose.shift_cm, 3),
                                                      max_angle_deg=round(pose.max_angle_deg, 3)))
    return replace(plain, score=score, refined_sheet=again.sheet, refine_seconds=pose.seconds if first_view else 0.0)


def _held_out_poses(project: Project, avatar: Any, cfg: EvalConfig, is_train: bool, scored: Any
                    ) -> tuple[Any, str | None]:
    """(the fit's poses of the held-out frames (`fit.held_out_poses.HeldOutPoses`) or None, a warning or None): used
    for the project's own held-out frames unless `held_out_poses` is "ingest" (module docstring)."""
    from avatarctl.fit.held_out_poses import load_held_out_poses

    if is_train or scored is not None or cfg.held_out_poses == "ingest":
        return None, None
    return load_held_out_poses(project.paths.fit, avatar.step)


def _held_out_record(held: Any, frames: list[int]) -> dict[str, Any] | None:
    """metrics.json "held_out_poses": which scored frames the fit's poses drove, and how they were found."""
    from avatarctl.fit.held_out_poses import FILE_NAME, PROTOCOL

    if held is None:
        return None
    posed = [f for f in frames if f in held]
    return {"source": f"fit/{FILE_NAME}", "frames": len(posed), "of": len(frames), "views": list(held.views),
            "steps": held.steps, "checkpoint_step": held.step, "protocol": PROTOCOL} if posed else None


def _held_out_gains(avatar: Any, cap: Any, cfg: EvalConfig, views: list[str]) -> dict[str, np.ndarray]:
    """{view: gains [3]} of the scored views the avatar did not train on that ingest estimated (module docstring)."""
    if cfg.camera_colour == "off" or cap.camera_colour is None:
        return {}
    trained = set(avatar.capture.split.train_views)
    return {v: g for v in views if v not in trained and (g := cap.camera_colour.of(v)) is not None}


def _as_camera_sees(avatar: Any, view: str, rgb: np.ndarray, alpha: np.ndarray, gain: np.ndarray | None
                    ) -> np.ndarray:
    """[H, W, 3] the render as camera `view` sees it (module docstring): through its learned colour transform when
    the avatar has one for it (a training camera, `model.colour.enabled`), through `gain` [3] (a held-out camera's,
    from ingest) when given, else as rendered (the training cameras' mean colour)."""
    colour = _camera_colour(avatar, view, gain)
    if colour is None:
        return rgb
    from avatarctl.evaluate.colour import apply_colour

    g, offset = colour
    bg = np.asarray(avatar.background, np.float32)
    return np.clip(apply_colour(rgb, alpha, bg, g, offset), 0.0, 1.0).astype(np.float32)


def _camera_colour(avatar: Any, view: str, gain: np.ndarray | None) -> tuple[np.ndarray, np.ndarray] | None:
    """(gain [3], offset [3]) camera `view` sees the avatar's colours through (`_as_camera_sees`), None: identity."""
    colour = avatar.model.camera_colour
    learned = colour.of(view) if colour is not None else None
    if learned is not None:
        return tuple(np.asarray(x, np.float32) for x in learned)
    return None if gain is None else (np.asarray(gain, np.float32), np.zeros(3, np.float32))


def _matched_score(rgb: np.ndarray, alpha: np.ndarray, gt: np.ndarray, gt_mask: np.ndarray, background: Any,
                   mask: np.ndarray, crop: tuple[int, int, int, int]) -> Any:
    """NeRF-W's colour-matched score of one image (`MatchedScore`; `MATCHED_PROTOCOL`), None when a half is empty.
    The transform is fitted where render and mask agree on the subject: pixels one covers and the other does not
    are silhouette errors no colour can fix, and would pull the gain towards 0 (measured on 20 s fits of synth
    realistic's clean twin, 6 images: fitted over the whole left half the figure lost 0.71 dB against the plain one
    on the same pixels, fitted on the shared foreground 0.06 dB)."""
    from avatarctl.evaluate.colour import apply_colour, estimate_colour, halves
    from avatarctl.evaluate.metrics import mse
    from avatarctl.evaluate.report import MatchedScore

    left, right = halves(mask, crop)
    if not left.any() or not right.any():
        return None
    bg = np.asarray(background, np.float32)
    gain, offset = estimate_colour(rgb, alpha, gt, bg, left & (alpha >= 0.5) & np.asarray(gt_mask, bool))
    matched = np.clip(apply_colour(rgb, alpha, bg, gain.astype(np.float32), offset.astype(np.float32)), 0.0, 1.0)
    return MatchedScore(mse=mse(matched, gt, right), plain_mse=mse(rgb, gt, right),
                        gain=[round(float(g), 5) for g in gain], offset=[round(float(o), 5) for o in offset])


def _test_capture(avatar: Any, test_project: str) -> Any:
    """The test project's capture (`ProjectCapture`) with its body fits given the avatar's body shape."""
    from dataclasses import replace

    from avatarctl.io.motion_files import adopt_subject
    from avatarctl.io.project_io import load_project_capture

    test = load_project_capture(Project.open(test_project))
    if test.body_model != avatar.capture.body_model:
        raise InputError(f"--test-project's fits are {test.body_model}, the avatar's {avatar.capture.body_model}",
                         where=str(test_project), fix=f"ingest it with --body-model {avatar.capture.body_model}")
    return replace(test, motion=adopt_subject(test.motion, avatar.capture.motion))


def _gt_geometry(project: Project, region: str) -> Any:
    """The source capture's ground-truth geometry (`io.gt_geometry`), or None; required for garment / body."""
    from avatarctl.io.gt_geometry import open_gt_geometry

    geometry = open_gt_geometry(project.manifest.source.path)
    if geometry is None and region != "all":
        raise InputError(f"--region {region} needs the capture's ground-truth garment geometry, and "
                         f"{project.manifest.source.path} has none", where="--region",
                         fix="use --region all, edge or inner (the masks' silhouette: any capture), or a capture "
                             "made by `avatarctl synth` (gt/geometry.npz) or a 4D-DRESS take (its labelled scans)")
    return geometry


def _garment_errors(rgb: np.ndarray, gt: np.ndarray, mask: np.ndarray, cam: Any, geometry: Any, frame: int
                    ) -> tuple[dict[str, float], dict[str, int]]:
    """`_part_errors` of the garment / body split of the protocol's `mask` (`evaluate.regions`)."""
    from avatarctl.evaluate.regions import GEOMETRY_REGIONS, garment_mask, split_region

    g = geometry.frame(frame)
    parts = split_region(mask, garment_mask(cam, g.body_vertices, g.body_faces, g.garment_vertices, g.garment_faces))
    return _part_errors(rgb, gt, parts, GEOMETRY_REGIONS)


def _part_errors(rgb: np.ndarray, gt: np.ndarray, parts: dict[str, np.ndarray], names: tuple[str, ...]
                 ) -> tuple[dict[str, float], dict[str, int]]:
    """({n: mse, n + "_flat": mse}, {n: pixels}) for each region n of `names` ([H, W] bool masks in `parts`);
    *_flat: the error of the region's best flat colour (its mean ground truth)."""
    from avatarctl.evaluate.metrics import mse

    err = {n: mse(rgb, gt, parts[n]) if parts[n].any() else 0.0 for n in names}
    # the region's best flat colour (its mean ground-truth colour): the floor a useful render must beat
    err.update({f"{n}_flat": float(((gt[parts[n]] - gt[parts[n]].mean(0)) ** 2).mean()) if parts[n].any() else 0.0
                for n in names})
    return err, {n: int(parts[n].sum()) for n in names}


def _finite_mean(a: np.ndarray) -> float:
    return float(np.mean(a)) if len(a) else float("nan")


def _protocol_details(cfg: EvalConfig) -> str:
    if cfg.protocol == "mpmavatar_4d_dress":
        return ("MPMAvatar's eval.py for 4D-DRESS: both images times the ground-truth mask eroded 5x (3x3) and blurred "
                "(5x5 Gaussian), no near-white cut; PSNR and SSIM over every pixel")
    if cfg.protocol == "mpmavatar":
        return ("MPMAvatar's eval.py: near-white pixels (rgb mean > 0.9) of each image zeroed, both images times the "
                "ground-truth mask eroded 5x (3x3) and blurred (5x5 Gaussian); PSNR and SSIM over every pixel")
    if cfg.protocol == "bbox":
        return (f"PSNR over pixels inside the projection of the posed body mesh's 3D box grown by {cfg.bbox_pad} m "
                "(mask_at_box); SSIM on the image cropped to that polygon's bounding rectangle")
    return "PSNR and SSIM over every pixel of the image"


def compare(projects: list[str | Path], split: str | None = None, protocol: str | None = None) -> list[Any]:
    """`avatarctl eval --compare`: one `ComparisonRow` per project from its latest metrics.json (nothing rendered)."""
    from avatarctl.evaluate.compare import compare as compare_projects

    return compare_projects(projects, split, protocol)
