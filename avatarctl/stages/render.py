"""The render stage (`avatarctl render PROJECT`): a fitted avatar -> PNG frames, an MP4 and a config record.

Steps:
1. load the fitted avatar (`stages.common.load_fitted`);
2. choose the motion: the project's own frames (training frames render with the cVAE latent z = mu, novel frames
   with z = 0, paper Sec. 4.1; a held-out frame the fit posed, fit/held_out_poses.py, with the fit's pose) or a
   motion file (`--poses`, always novel: z = 0 unless `--latent sample`; any rig:
   anny / AMASS npz, AIST++ pkl, BVH, retargeted onto the avatar's body model when made for another,
   `io.motion_convert`); a motion file's body shape is replaced by the avatar's own (`adopt_subject`) and, by default, its translation
   is moved so its first frame starts where the avatar's first training frame stands (`recenter`);
3. choose the cameras: capture views (`views`, scaled to `resolution`) or an orbit (`orbit` views over one turn
   around the subject's smoothed box centre, `trajectories.orbit_cameras`);
4. render each (frame, camera) with the sparse, chunked view renderer (`render.engine.render_view`), which only
   casts rays that can reach a node's support and bounds memory by `max_rays_per_chunk`;
5. write `render/<name>/frames/*.png`, `video.mp4` (H.264 / yuv420p) and `config.json` into a temporary directory,
   rename it into place (`atomic_dir`) and record the stage in the manifest.

Several ranks (`nproc`, or a torchrun launch; `stages.common.run_ranked`): rank r renders the video frames
seq = r, r + N, ... (all views of a frame on one rank), writing their PNGs into rank 0's temporary directory (the
project directory is shared) and each video tile as a `.npy` part; rank 0 gathers the image records, encodes the
video from the parts in order and writes the rest. The files are those of one process (same renders, same
encoders); only the timings differ.

Image naming: `frames/<seq:05d>_<view>_<frame:06d>.png`, where `seq` is the video frame the image belongs to (several
views of one frame share a `seq` and are tiled side by side in the video).
"""

from __future__ import annotations

import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from avatarctl.errors import InputError
from avatarctl.frames import select_frames
from avatarctl.geometry.cameras import Camera
from avatarctl.lists import split_list
from avatarctl.project import Project, check_name, now_iso
from avatarctl.progress import ProgressReport, ProgressFn
from avatarctl.stages.common import check_knockout, check_latent_mode, fitted_held_out_poses, frame_node_state, \
    knocked_out, latent_for, load_fitted, motion_for_avatar, open_fitted, rank_device_name, run_ranked, select_views, \
    writing

SCHEMA_VERSION = 1
DEFAULT_MAX_RAYS = 8192


def parse_background(spec: str, fit_background: tuple[float, float, float]) -> tuple[tuple[float, float, float], bool]:
    """'fit' | 'black' | 'white' | 'transparent' | 'r,g,b' (0-1 or 0-255) -> (rgb in [0, 1], transparent?)."""
    s = spec.strip().lower()
    if s == "fit":
        return tuple(float(c) for c in fit_background), False  # type: ignore[return-value]
    if s == "black":
        return (0.0, 0.0, 0.0), False
    if s == "white":
        return (1.0, 1.0, 1.0), False
    if s == "transparent":
        return (0.0, 0.0, 0.0), True
    try:
        vals = list(split_list(s, float))
        if len(vals) != 3:
            raise ValueError
    except ValueError:
        raise InputError(f"cannot parse background {spec!r}", where="--background",
                         fix="use fit | black | white | transparent | r,g,b") from None
    if max(vals) > 1.0:
        vals = [v / 255.0 for v in vals]
    if not all(0.0 <= v <= 1.0 for v in vals):
        raise InputError(f"background {spec!r} outside [0, 1] / [0, 255]", where="--background", fix="e.g. 1,1,1")
    return (vals[0], vals[1], vals[2]), False


# ---- config / result ---------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class RenderConfig:
    """What `avatarctl render` renders. Saved as `render/<name>/config.json` and in the manifest."""

    name: str = "default"  # output folder render/<name>
    poses: str | None = None  # motion file (anny npz / AMASS npz); None = the project's own frames
    frames: str | None = None  # frame selection (see `avatarctl.frames`); None = all
    views: tuple[str, ...] = ()  # capture cameras; () and orbit == 0 = the first held-out view
    orbit: int = 0  # > 0: that many orbit cameras over one turn instead of capture views
    elevation: float | None = None  # orbit elevation, degrees; None = mean elevation of the capture cameras
    radius: float | None = None  # orbit radius, metres; None = mean distance of the capture cameras
    latent: str = "auto"  # auto (mean for training frames, zero otherwise) | mean | zero | sample
    seed: int = 0  # for latent "sample"
    resolution: int | None = None  # longer image side, pixels; None = the capture's
    background: str = "fit"  # fit | black | white | transparent | r,g,b
    fps: float | None = None  # video frame rate; None = the motion's fps / frame step
    recenter: bool = True  # --poses: move the motion to where the avatar's first training frame stands
    max_rays_per_chunk: int = DEFAULT_MAX_RAYS  # rays per model call (memory bound)
    device: str = "auto"  # auto | cpu | cuda
    checkpoint: str | None = None  # None = fit/checkpoints/latest.pt
    knockout: tuple[str, ...] = ()  # render-time knockout of a trained model: delta-n and/or embedding (Fig. 3)

    def __post_init__(self) -> None:
        object.__setattr__(self, "views", tuple(self.views))
        object.__setattr__(self, "knockout", check_knockout(tuple(self.knockout)))
        check_name(self.name, "render name")
        check_latent_mode(self.latent)
        if self.orbit < 0:
            raise InputError(f"--orbit must be >= 0, got {self.orbit}", where="--orbit", fix="e.g. --orbit 36")
        if self.orbit and self.views:
            raise InputError("--views and --orbit are exclusive", fix="pass one of them")
        if self.resolution is not None and not 8 <= self.resolution <= 8192:
            raise InputError(f"--resolution {self.resolution} outside [8, 8192]", where="--resolution",
                             fix="e.g. --resolution 512")
        if self.radius is not None and not self.radius > 0:
            raise InputError(f"--radius must be > 0 metres, got {self.radius}", where="--radius", fix="e.g. 3.0")
        if self.elevation is not None and not -89 <= self.elevation <= 89:
            raise InputError(f"--elevation {self.elevation} outside [-89, 89] degrees", where="--elevation",
                             fix="e.g. --elevation 10")
        if self.fps is not None and not self.fps > 0:
            raise InputError(f"--fps must be > 0, got {self.fps}", where="--fps", fix="e.g. --fps 30")
        if self.max_rays_per_chunk < 64:
            raise InputError(f"max rays per chunk {self.max_rays_per_chunk} < 64", fix="e.g. 8192")
        parse_background(self.background, (0.0, 0.0, 0.0))  # validate the syntax early

    def to_json(self) -> dict[str, Any]:
        d = asdict(self)
        d["views"] = list(self.views)
        d["knockout"] = list(self.knockout)
        return {"schema_version": SCHEMA_VERSION, **d}


@dataclass(frozen=True)
class RenderedImage:
    file: str  # relative to the render folder
    seq: int  # video frame index
    frame: int  # frame number (project capture frame or motion-file frame)
    view: str  # capture camera or orbit camera name
    latent: str  # mean | zero | sample
    seconds: float
    rays: int  # rays actually rendered


@dataclass
class RenderResult:
    out_dir: Path
    video: Path
    images: list[RenderedImage]
    width: int  # of one image
    height: int
    video_size: tuple[int, int]  # (W, H)
    fps: float
    seconds: float  # whole stage
    render_seconds: float  # sum over images of render_view time
    checkpoint_step: int
    background: tuple[float, float, float]
    motion_source: str  # "project" or the motion file
    retarget: str | None = None  # one line when the motion file was retargeted onto the avatar's body model
    latent_counts: dict[str, int] = field(default_factory=dict)

    @property
    def seconds_per_image(self) -> float:
        return self.render_seconds / max(len(self.images), 1)


# ---- the stage -------------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class _Plan:
    """Resolved work: which motion rows, cameras and latent modes."""

    motion: Any  # BodyMotion
    frames: list[int]
    training: list[bool]  # [frames] whether each frame is a training frame of the avatar
    latents: list[str]  # [frames] mean | zero | sample
    shots: list[tuple[int, int, Camera]]  # (seq, frame position, camera)
    views_per_seq: int
    fps: float
    source: str
    retarget: str | None  # what retargeting did to the motion file, None if it was made for the avatar's body


def run(project_dir: str | Path, cfg: RenderConfig, progress: ProgressFn | None = None, *,
        nproc: int = 1, wait: bool = False) -> RenderResult | None:
    """Run the render stage on `project_dir` (see the module docstring), on `nproc` ranks. Returns what was written
    (None on the ranks > 0 of a torchrun launch). Holds the lock of `render/<name>`; `wait`: for another command
    writing it to finish, instead of refusing (`BusyError`)."""
    out_dir = Project.open(project_dir).paths.render(cfg.name)
    with writing(out_dir, f"render --name {cfg.name}", wait, sweep=True):
        return run_ranked(_run, nproc, (str(project_dir), cfg), progress, cfg.device, "render")


def _run(env: Any, progress: ProgressFn | None, project_dir: str, cfg: RenderConfig) -> RenderResult | None:
    import contextlib

    import torch

    from avatarctl.atomic import atomic_dir, write_json
    from avatarctl.dist import active, broadcast_from_main, gather_to_main
    from avatarctl.render.video import tile, write_video

    started = now_iso()
    t_start = time.perf_counter()
    project = open_fitted(project_dir, cfg.checkpoint, cfg.views, cfg.poses)
    avatar = load_fitted(project, rank_device_name(env, cfg.device), cfg.checkpoint)
    background, transparent = parse_background(cfg.background, avatar.background)
    plan = _plan(avatar, cfg)
    held = fitted_held_out_poses(avatar) if cfg.poses is None else None  # the project's frames: the fit's poses
    out_dir = project.paths.render(cfg.name)

    images: list[RenderedImage] = []
    total = len(plan.shots)
    t0 = time.perf_counter()
    bg8 = tuple(int(round(c * 255)) for c in background)
    world = env.world_size if active(env) else 1
    main = env is None or env.is_main

    def shots(tmp: Path, mine: list[int]):
        """Render the shots `mine` (indices into plan.shots), write each PNG; yield (index, record, uint8 image)."""
        state_cache: tuple[int, Any] | None = None
        for n, i in enumerate(mine):
            seq, pos, cam = plan.shots[i]
            if state_cache is None or state_cache[0] != pos:
                state_cache = (pos, knocked_out(avatar, frame_node_state(
                    avatar, plan.motion.select([pos]), plan.frames[pos], plan.training[pos], plan.latents[pos],
                    cfg.seed, held), cfg.knockout))
            image, rgb8 = _render_shot(avatar, state_cache[1], plan, i, background, transparent, cfg, tmp)
            if progress is not None:
                progress(ProgressReport(stage="render", done=min((n + 1) * world, total), total=total,
                                        seconds=time.perf_counter() - t0))
            yield i, image, rgb8

    def video_frames(rows: Any):
        """One tiled video frame per `seq` from (index, record, uint8 image) in shot order (streamed, not held)."""
        row: list[np.ndarray] = []
        for i, image, rgb8 in rows:
            images.append(image)
            row.append(rgb8)
            if i + 1 == len(plan.shots) or plan.shots[i + 1][0] != image.seq:
                yield tile(row, columns=len(row), pad_color=bg8)
                row = []

    with atomic_dir(out_dir) if main else contextlib.nullcontext() as tmp:
        if main:
            (tmp / "frames").mkdir()
        tmp = broadcast_from_main(tmp, env)
        if world == 1:
            rows: Any = shots(tmp, list(range(total)))
        else:  # this rank's video frames, then rank 0 encodes from the parts every rank wrote
            parts = tmp / ".parts"
            parts.mkdir(exist_ok=True)
            mine = []
            for i, image, rgb8 in shots(tmp, [i for i, s in enumerate(plan.shots) if s[0] % world == env.rank]):
                np.save(parts / f"{i:07d}.npy", rgb8)
                mine.append((i, image))
            gathered = gather_to_main(mine, env)
            if not main:
                return None
            rows = ((i, image, np.load(parts / f"{i:07d}.npy")) for i, image in sorted(sum(gathered, [])))
        vinfo = write_video(video_frames(rows), tmp / "video.mp4", fps=plan.fps, pad_color=bg8)
        if world > 1:
            shutil.rmtree(tmp / ".parts")
        render_seconds = float(sum(im.seconds for im in images))
        h, w = plan.shots[0][2].height, plan.shots[0][2].width
        latent_counts: dict[str, int] = {}
        for im in images:
            latent_counts[im.latent] = latent_counts.get(im.latent, 0) + 1
        record = {
            "config": cfg.to_json(),
            "checkpoint": str(avatar.checkpoint) if avatar.checkpoint else None,
            "checkpoint_step": avatar.step,
            "motion_source": plan.source,
            "retarget": plan.retarget,
            "background": list(background),
            "transparent": transparent,
            "image_size": [w, h],
            "video": {"file": "video.mp4", "frames": vinfo.frames, "size": [vinfo.width, vinfo.height],
                      "fps": vinfo.fps, "codec": "h264 (libx264)", "pix_fmt": vinfo.pix_fmt},
            "cameras": [c.to_json() for c in _unique_cameras(plan.shots)],
            "images": [asdict(im) for im in images],
            "knockout": list(cfg.knockout),
            "model": {"sparse": bool(avatar.model_config.sparse), "variant": avatar.model_config.variant,
                      "num_nodes": avatar.model_config.num_nodes,
                      "samples_per_ray": avatar.model_config.samples_per_ray},
            "timing": {"render_seconds": round(render_seconds, 3),
                       "seconds_per_image": round(render_seconds / max(len(images), 1), 4),
                       "device": str(avatar.device), "torch_threads": torch.get_num_threads()},
            "created": now_iso(),
        }
        write_json(tmp / "config.json", record)
    seconds = time.perf_counter() - t_start
    result = RenderResult(out_dir=out_dir, video=out_dir / "video.mp4", images=images, width=w, height=h,
                          video_size=(vinfo.width, vinfo.height), fps=plan.fps, seconds=seconds,
                          render_seconds=render_seconds, checkpoint_step=avatar.step, background=background,
                          motion_source=plan.source, retarget=plan.retarget, latent_counts=latent_counts)
    project.record("render", config=cfg.to_json(), outputs=[out_dir], started=started,
                   summary={"name": cfg.name, "images": len(images), "size": f"{w}x{h}",
                            "knockout": list(cfg.knockout),
                            "seconds_per_image": round(result.seconds_per_image, 3), "video": "video.mp4",
                            "checkpoint_step": avatar.step, "motion": plan.source})
    return result


def _plan(avatar: Any, cfg: RenderConfig) -> _Plan:
    """Resolve motion, frames, latent modes and cameras from the config."""
    cap = avatar.capture
    retarget: str | None = None
    train_set = set(int(f) for f in avatar.train_frames)
    if cfg.poses is None:
        motion = cap.motion
        frames = select_frames(cfg.frames, cap.frames, train=cap.split.train_frames, test=cap.split.test_frames)
        training = [f in train_set for f in frames]
        source = "project"
    else:
        motion, retarget = motion_for_avatar(avatar, cfg.poses, cfg.recenter)
        frames = select_frames(cfg.frames, [int(f) for f in motion.frame_index])
        training = [False] * len(frames)
        source = str(cfg.poses)
    motion = motion.for_frames(frames)
    latents = [latent_for(cfg.latent, is_train) for is_train in training]

    cams = avatar.capture.cameras
    step = int(np.median(np.diff(frames))) if len(frames) > 1 else 1
    fps = cfg.fps or max(float(motion.fps) / max(step, 1), 1.0)
    if cfg.orbit:
        shots, views_per_seq = _orbit_shots(avatar, cfg, motion, frames, list(cams.values())), 1
    else:
        names = cfg.views or (cap.split.test_views[:1] or cap.split.train_views[:1] or [next(iter(cams))])
        views = [cams[n].pinhole() for n in select_views(tuple(names), cams)]
        if cfg.resolution is not None:
            views = [_scaled_to(c, cfg.resolution) for c in views]
        shots = [(i, i, c) for i in range(len(frames)) for c in views]
        views_per_seq = len(views)
    return _Plan(motion=motion, frames=frames, training=training, latents=latents, shots=shots,
                 views_per_seq=views_per_seq, fps=fps, source=source, retarget=retarget)


def _scaled_to(cam: Camera, longer_side: int) -> Camera:
    factor = longer_side / max(cam.width, cam.height)
    return cam if abs(factor - 1.0) < 1e-9 else cam.scaled(factor)


def _orbit_shots(avatar: Any, cfg: RenderConfig, motion: Any, frames: list[int], capture_cams: list[Camera]
                 ) -> list[tuple[int, int, Camera]]:
    """`cfg.orbit` cameras over one turn; video frame k shows pose frames[floor(k * F / orbit)]."""
    from avatarctl.render.trajectories import OrbitSpec, orbit_cameras, orbit_defaults, smooth_centers, up_from_cameras

    n, F = cfg.orbit, len(frames)
    pos = [min(k * F // n, F - 1) for k in range(n)]
    lo, hi = _boxes(avatar, motion)  # [frames, 3] each
    centers = smooth_centers((lo + hi) / 2.0)
    extent = float(np.max(np.linalg.norm(hi - lo, axis=1)) / 2.0)
    up = up_from_cameras(capture_cams)
    dist, elev, ref = orbit_defaults(capture_cams, centers[0], up)
    radius = cfg.radius or dist
    if radius <= extent * 1.05:
        raise InputError(f"orbit radius {radius:.2f} m is inside the subject (half-diagonal {extent:.2f} m)",
                         where="--radius", fix=f"use --radius larger than {extent * 1.2:.2f}")
    res = cfg.resolution or max(max(c.width, c.height) for c in capture_cams)
    spec = OrbitSpec(views=n, elevation_deg=cfg.elevation if cfg.elevation is not None else elev,
                     radius=radius, resolution=res)
    cams = orbit_cameras(spec, centers[pos], extent, up, radius, reference_dir=ref)
    return [(k, pos[k], cams[k]) for k in range(n)]


def _boxes(avatar: Any, motion: Any, chunk: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """[frames, 3] min / max corners of the posed body mesh, world metres."""
    lo, hi = [], []
    for s in range(0, motion.num_frames, chunk):
        v = avatar.body.pose(motion.select(slice(s, s + chunk))).vertices.detach().float().cpu().numpy()
        lo.append(v.min(axis=1))
        hi.append(v.max(axis=1))
    return np.concatenate(lo).astype(np.float64), np.concatenate(hi).astype(np.float64)


def _render_shot(avatar: Any, state: Any, plan: _Plan, i: int, background: tuple[float, float, float],
                 transparent: bool, cfg: RenderConfig, tmp: Path) -> tuple[RenderedImage, np.ndarray]:
    """Render shot i of the plan, write its PNG into `tmp`; -> its record and its uint8 RGB [H, W, 3] (the video's)."""
    from avatarctl.render.engine import render_view
    from avatarctl.render.images import to_uint8, write_png

    seq, pos, cam = plan.shots[i]
    view = render_view(avatar.model, state, 0, cam, background, max_rays_per_chunk=cfg.max_rays_per_chunk)
    frame = plan.frames[pos]
    fname = f"frames/{seq:05d}_{cam.name}_{frame:06d}.png"
    write_png(tmp / fname, view.rgb, view.alpha if transparent else None)
    return (RenderedImage(file=fname, seq=seq, frame=frame, view=cam.name, latent=plan.latents[pos],
                          seconds=round(view.seconds, 4), rays=int(view.rays)), to_uint8(view.rgb))


def _unique_cameras(shots: list[tuple[int, int, Camera]]) -> list[Camera]:
    seen: dict[str, Camera] = {}
    for _, _, c in shots:
        seen.setdefault(c.name, c)
    return list(seen.values())
