"""The view stage (`avatarctl view PROJECT`): a local web viewer of a fitted avatar (viser, the `view` extra).

Steps:
1. load the fitted avatar (`stages.common.load_fitted`, CPU or GPU);
2. the motions: the project's training and test frames (labelled), and each `--poses` file (made to drive the avatar
   as `render --poses` does: `motion_for_avatar`); any other motion file can be loaded from the page (the same
   loader). The latent of a frame follows `--latent` / the GUI with the "auto" rule (z = mu for training frames, 0
   otherwise); "mean" on a frame that is not a training frame falls back to 0;
3. a `viewer.session.ViewerSession` behind a `viewer.controller.ViewerController` (the panel's state, play, render,
   save video), served by one of two pages: a Gaussian-field avatar by our own page (`viewer.splat_server`: the
   browser draws each frame's posed Gaussians, sent over a websocket), a ray-marched one by viser's
   (`viewer.server`: progressive server renders, with its posed mesh (`export.mesh`, coarse voxel) drawn by the
   page meanwhile, `--mesh-preview`). The orbit camera starts at the first held-out camera (its position and
   vertical field of view), looking at the subject;
4. "save video" in the page runs `avatarctl render` in a child process for the motion, latent and camera path shown
   (`render/view-<n>`: the only thing the viewer writes into the project);
5. `ready(url)` is called once the server listens; the stage then serves until `stop` is set (or Ctrl-C reaches
   the caller), and stops the server, its threads and a running video on the way out.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from avatarctl.errors import AvatarError, InputError
from avatarctl.stages.common import check_latent_mode, fitted_held_out_poses, frame_node_state, latent_for, \
    load_fitted, motion_for_avatar, open_fitted


@dataclass(frozen=True)
class ViewConfig:
    """What `avatarctl view` serves."""

    host: str = "127.0.0.1"  # 0.0.0.0 to serve other machines
    port: int = 8080
    resolution: int | None = None  # longer image side at full quality (the GUI can change it); None = 512 on a GPU,
    #                                256 on the CPU (a 256² frame takes ~8 s of one core on synth small, 512² ~33 s)
    preview_scale: float = 0.25  # resolution factor while the camera moves
    settle_s: float = 0.3  # seconds still before the full-resolution render
    latent: str = "auto"  # auto | mean | zero | sample (the GUI can change it)
    seed: int = 0  # for latent "sample"
    poses: tuple[str, ...] = ()  # motion files the page offers (a str is one file); the first is shown first;
    #                              () = the project's frames first
    recenter: bool = True
    fps: float | None = None  # play speed, frames per second; None = the motion's frame rate
    mesh_preview: bool = True  # ray-marched fields: the page draws the frame's posed mesh while the render refines
    mesh_voxel: float = 0.016  # grid spacing of that mesh, metres (coarser than `export`'s 8 mm: seconds, not 30)
    max_rays_per_chunk: int = 4096  # rays per model call; also how often a stale render can be abandoned
    device: str = "auto"
    checkpoint: str | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "poses", (self.poses,) if isinstance(self.poses, str) else tuple(self.poses or ()))
        check_latent_mode(self.latent)
        if not 1 <= self.port <= 65535:
            raise InputError(f"--port {self.port} outside [1, 65535]", where="--port", fix="e.g. --port 8080")
        if self.resolution is not None and not 16 <= self.resolution <= 2048:
            raise InputError(f"--resolution {self.resolution} outside [16, 2048]", where="--resolution",
                             fix="e.g. --resolution 512")
        if not 0 < self.preview_scale <= 1:
            raise InputError(f"preview scale {self.preview_scale} outside (0, 1]", fix="e.g. 0.25")
        if not 0.002 <= self.mesh_voxel <= 0.1:
            raise InputError(f"mesh voxel {self.mesh_voxel} m outside [0.002, 0.1]", fix="e.g. 0.016")
        if self.fps is not None and not self.fps > 0:
            raise InputError(f"--fps must be > 0, got {self.fps}", where="--fps", fix="e.g. --fps 10")
        if self.max_rays_per_chunk < 64:
            raise InputError(f"max rays per chunk {self.max_rays_per_chunk} < 64", fix="e.g. 4096")


@dataclass(frozen=True)
class ViewerSetup:
    """What `prepare` builds: the render session and where the camera starts (also used without a server)."""

    session: Any  # viewer.session.ViewerSession
    initial: Any  # viewer.server.InitialView
    avatar: Any  # LoadedAvatar


def prepare(project_dir: str | Path, cfg: ViewConfig) -> ViewerSetup:
    """Steps 1-3 without a server: the session (render, splats, mesh, motions) and where the camera starts."""
    from avatarctl.render.trajectories import up_from_cameras
    from avatarctl.viewer.server import InitialView
    from avatarctl.viewer.session import ViewerSession

    project = open_fitted(project_dir, cfg.checkpoint, (), cfg.poses[0] if cfg.poses else None)
    avatar = load_fitted(project, cfg.device, cfg.checkpoint)
    cap = avatar.capture
    first = _motion(avatar, cfg, cfg.poses[0] if cfg.poses else PROJECT)
    mesh_fn = _mesh_fn(avatar, cfg) if cfg.mesh_preview and not avatar.model.field_kind.splats else None
    session = ViewerSession(avatar.model, first, avatar.background, cfg.max_rays_per_chunk,
                            load_motion=lambda name: _motion(avatar, cfg, name), mesh_fn=mesh_fn)
    cams = list(cap.cameras.values())
    start = cap.cameras[(cap.split.test_views or cap.split.train_views or list(cap.cameras))[0]]
    state = session.state(0, "zero")
    centers = state.centers[0].detach().float().cpu().numpy()
    center = (centers.min(0) + centers.max(0)) / 2.0
    initial = InitialView(position=tuple(float(c) for c in start.center), look_at=tuple(float(c) for c in center),
                          up=tuple(float(c) for c in up_from_cameras(cams)),
                          fov_y=2.0 * float(np.arctan((start.height / 2.0) / start.K[1, 1])))
    return ViewerSetup(session=session, initial=initial, avatar=avatar)


PROJECT = "project"  # the motion name of the project's own frames


def _motion(avatar: Any, cfg: ViewConfig, name: str) -> Any:
    """The `ViewerMotion` of the project's frames (`PROJECT`) or of a motion file (step 2)."""
    from avatarctl.viewer.session import ViewerFrame, ViewerMotion

    cap = avatar.capture
    train_set = set(int(f) for f in avatar.train_frames)
    note, held = None, None
    if name == PROJECT:
        held = fitted_held_out_poses(avatar)  # the held-out frames at the fit's poses, where it posed them
        motion = cap.motion
        test = set(int(f) for f in cap.split.test_frames)
        frames = [ViewerFrame(label=f"frame {f} ({'train' if f in train_set else 'test'})", frame=f,
                              source="train" if f in train_set else "test")
                  for f in cap.frames if f in train_set or f in test]
        step = int(np.median(np.diff([f.frame for f in frames]))) if len(frames) > 1 else 1
    else:
        path = Path(name).expanduser()
        if not path.is_file():
            raise InputError(f"no motion file {name}", where="--poses", fix="give the path of an existing file")
        motion, note = motion_for_avatar(avatar, path, cfg.recenter)
        frames = [ViewerFrame(label=f"{path.name} frame {int(f)}", frame=int(f), source="motion")
                  for f in motion.frame_index]
        step = 1
    if not frames:
        raise InputError(f"no frames to show in {name}", fix="check the project's split / the motion file")
    fps = max(float(motion.fps) / max(step, 1), 1.0) if float(motion.fps) > 0 else 30.0

    def state_fn(pos: int, mode: str) -> Any:
        fr = frames[pos]
        is_train = fr.source == "train"
        try:
            latent = latent_for(mode, is_train)
        except AvatarError:  # "mean" on a novel frame: the viewer shows the novel-pose latent rather than failing
            latent = "novel"
        return frame_node_state(avatar, motion.for_frames([fr.frame]), fr.frame, is_train, latent,
                                cfg.seed, held)

    return ViewerMotion(name=name, frames=frames, state_fn=state_fn, fps=fps, note=note)


def _mesh_fn(avatar: Any, cfg: ViewConfig) -> Callable[[Any], Any]:
    """The posed mesh of a node state (export.mesh at `mesh_voxel`), for the page to draw (ray-marched fields)."""
    from avatarctl.export.mesh import DEFAULT_THRESHOLD, extract_mesh, head_on_bake, slrf_density, slrf_ray_colour

    model = avatar.model

    def mesh(state: Any) -> Any:
        colour = head_on_bake(slrf_ray_colour(model, state), 2.0 * cfg.mesh_voxel)
        return extract_mesh(slrf_density(model, state), colour, state.centers[0].detach().float().cpu().numpy(),
                            float(model.cfg.support_radius), cfg.mesh_voxel, DEFAULT_THRESHOLD)[0]

    return mesh


@dataclass
class RenderJob:
    """A running `avatarctl render` child process ("save video"); the server polls it."""

    proc: Any  # subprocess.Popen
    out_dir: Path
    log: Path

    def poll(self) -> str | None:
        code = self.proc.poll()
        if code is None:
            return None
        if code == 0 and (self.out_dir / "video.mp4").is_file():
            return f"video saved: {self.out_dir / 'video.mp4'}"
        last = [s for s in self.log.read_text(errors="replace").splitlines() if s.strip()][-1:] or ["(no output)"]
        return f"save video failed (exit {code}): {last[0][:200]}"

    def progress(self) -> str:
        import re

        text = self.log.read_text(errors="replace") if self.log.is_file() else ""
        found = re.findall(r"(\d+)/(\d+)", text[-2000:])
        return f"{found[-1][0]}/{found[-1][1]} images" if found else "starting ..."

    def cancel(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except Exception:  # noqa: BLE001 - still alive after 10 s
                self.proc.kill()


def _video_fn(project_dir: Path, cfg: ViewConfig) -> Callable[[str, str, str], RenderJob]:
    """Step 4: start `avatarctl render` for (motion, latent, camera path) into a fresh render/view-<n>."""
    import subprocess
    import sys

    from avatarctl.project import Project

    def start(motion: str, latent: str, camera_path: str) -> RenderJob:
        paths = Project.open(project_dir).paths
        n = 1
        while paths.render(f"view-{n}").exists():
            n += 1
        name = f"view-{n}"
        argv = [sys.executable, "-m", "avatarctl", "render", str(project_dir), "--name", name, "--latent", latent,
                "--seed", str(cfg.seed), "--device", cfg.device]
        if motion != PROJECT:
            argv += ["--poses", motion] + ([] if cfg.recenter else ["--no-recenter"])
        if camera_path == "orbit":
            argv += ["--orbit", "36"]
        if cfg.checkpoint:
            argv += ["--checkpoint", cfg.checkpoint]
        log = paths.render(name).parent / f".{name}.log"
        log.parent.mkdir(parents=True, exist_ok=True)
        with log.open("w") as f:
            proc = subprocess.Popen(argv, stdout=f, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
        return RenderJob(proc=proc, out_dir=paths.render(name), log=log)

    return start


@dataclass(frozen=True)
class ViewResult:
    """What a viewer session served."""

    url: str  # where it was served
    frames: int  # frames of the project's motion it offered
    gaussian: bool  # the avatar's field is the rasterized Gaussians (else ray-marched)
    background: tuple[float, float, float]  # the fit background, RGB in [0, 1]
    config: ViewConfig


def run(project_dir: str | Path, cfg: ViewConfig, ready: Callable[[str], None] | None = None,
        stop: threading.Event | None = None) -> ViewResult:
    """Serve the viewer until `stop` is set (or KeyboardInterrupt); returns what it served."""
    from avatarctl.viewer.controller import ViewerController
    from avatarctl.viewer.server import ViewerServer, import_viser
    from avatarctl.viewer.splat_server import SplatPageServer, import_websockets

    try:
        import_viser()
        import_websockets()
    except ImportError:
        raise InputError("the viewer needs the `viser` and `websockets` packages", where="avatarctl[view]",
                         fix="pip install 'avatarctl[view]'") from None
    setup = prepare(project_dir, cfg)
    gaussian = setup.session.gaussian
    resolution = cfg.resolution or (512 if setup.avatar.device.type == "cuda" or gaussian else 256)
    controller = ViewerController(setup.session, fps=cfg.fps, latent=cfg.latent, resolution=resolution,
                                  motions=(PROJECT, *cfg.poses), video=_video_fn(Path(project_dir), cfg))
    try:
        if gaussian:
            server: Any = SplatPageServer(controller, setup.initial, host=cfg.host, port=cfg.port)
        else:
            server = ViewerServer(controller, setup.initial, host=cfg.host, port=cfg.port,
                                  preview_scale=cfg.preview_scale, settle_s=cfg.settle_s)
    except OSError as e:
        controller.stop()
        raise InputError(f"cannot serve on {cfg.host}:{cfg.port} ({e.strerror or e})", where="--port",
                         fix="choose another --port") from None
    stop = stop or threading.Event()
    try:
        if ready is not None:
            ready(server.url)
        while not stop.wait(0.25):
            pass
    finally:
        server.stop()
    r, g, b = (float(c) for c in np.asarray(setup.avatar.background, float))
    return ViewResult(url=server.url, frames=len(setup.session.frames), gaussian=bool(gaussian), background=(r, g, b),
                      config=cfg)
