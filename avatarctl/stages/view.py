"""The view stage (`avatarctl view PROJECT`): a local web viewer of a fitted avatar (viser, the `view` extra).

Steps:
1. load the fitted avatar (`stages.common.load_fitted`, CPU or GPU);
2. the frame list: the project's training and test frames (labelled), or a motion file's frames (`--poses`, made to
   drive the avatar as `render --poses` does); the latent of a frame follows `--latent` / the GUI with the "auto"
   rule (z = mu for training frames, 0 otherwise); "mean" on a frame that is not a training frame falls back to 0;
3. a `viewer.session.ViewerSession` (the render callback: the sparse view renderer at the requested resolution)
   served by `viewer.server.ViewerServer`: orbit camera starting at the first held-out camera (its position and
   vertical field of view), looking at the subject; low resolution while the camera moves, full when it rests;
4. `ready(url)` is called once the server listens; the stage then serves until `stop` is set (or Ctrl-C reaches
   the caller), and stops the server and its render threads on the way out. Nothing is written to the project.
"""

from __future__ import annotations

import threading
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from avatarctl.errors import AvatarError, InputError
from avatarctl.stages.common import check_latent_mode, frame_node_state, latent_for, load_fitted, \
    motion_for_avatar, open_fitted


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
    poses: str | None = None  # motion file to play; None = the project's frames
    recenter: bool = True
    fps: float = 10.0  # play speed, frames per second
    max_rays_per_chunk: int = 4096  # rays per model call; also how often a stale render can be abandoned
    device: str = "auto"
    checkpoint: str | None = None

    def __post_init__(self) -> None:
        check_latent_mode(self.latent)
        if not 1 <= self.port <= 65535:
            raise InputError(f"--port {self.port} outside [1, 65535]", where="--port", fix="e.g. --port 8080")
        if self.resolution is not None and not 16 <= self.resolution <= 2048:
            raise InputError(f"--resolution {self.resolution} outside [16, 2048]", where="--resolution",
                             fix="e.g. --resolution 512")
        if not 0 < self.preview_scale <= 1:
            raise InputError(f"preview scale {self.preview_scale} outside (0, 1]", fix="e.g. 0.25")
        if not self.fps > 0:
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
    """Steps 1-2 and the session of step 3 (no server): the render callback of the viewer."""
    from avatarctl.render.trajectories import up_from_cameras
    from avatarctl.viewer.server import InitialView
    from avatarctl.viewer.session import ViewerFrame, ViewerSession

    project = open_fitted(project_dir, cfg.checkpoint, (), cfg.poses)
    avatar = load_fitted(project, cfg.device, cfg.checkpoint)
    cap = avatar.capture
    train_set = set(int(f) for f in avatar.train_frames)
    if cfg.poses is None:
        motion = cap.motion
        test = set(int(f) for f in cap.split.test_frames)
        frames = [ViewerFrame(label=f"frame {f} ({'train' if f in train_set else 'test'})", frame=f,
                              source="train" if f in train_set else "test")
                  for f in cap.frames if f in train_set or f in test]
    else:
        motion, _ = motion_for_avatar(avatar, cfg.poses, cfg.recenter)  # (the retarget note is not shown)
        frames = [ViewerFrame(label=f"motion frame {int(f)}", frame=int(f), source="motion")
                  for f in motion.frame_index]
    if not frames:
        raise InputError("no frames to show", where=str(project.root), fix="check the project's split / --poses")

    def state_fn(pos: int, mode: str) -> Any:
        fr = frames[pos]
        is_train = fr.source == "train"
        try:
            latent = latent_for(mode, is_train)
        except AvatarError:  # "mean" on a novel frame: the viewer shows the novel-pose latent rather than failing
            latent = "novel"
        return frame_node_state(avatar, motion.select(motion.rows_for([fr.frame])), fr.frame, is_train, latent,
                                cfg.seed)

    session = ViewerSession(avatar.model, frames, state_fn, avatar.background, cfg.max_rays_per_chunk)
    cams = list(cap.cameras.values())
    start = cap.cameras[(cap.split.test_views or cap.split.train_views or list(cap.cameras))[0]]
    verts = avatar.body.pose(motion.select(motion.rows_for([frames[0].frame]))).vertices[0].detach().cpu().numpy()
    center = (verts.min(0) + verts.max(0)) / 2.0
    initial = InitialView(position=tuple(float(c) for c in start.center), look_at=tuple(float(c) for c in center),
                          up=tuple(float(c) for c in up_from_cameras(cams)),
                          fov_y=2.0 * float(np.arctan((start.height / 2.0) / start.K[1, 1])))
    return ViewerSetup(session=session, initial=initial, avatar=avatar)


def run(project_dir: str | Path, cfg: ViewConfig, ready: Callable[[str], None] | None = None,
        stop: threading.Event | None = None) -> dict[str, Any]:
    """Serve the viewer until `stop` is set (or KeyboardInterrupt); returns a summary (frames, url, config)."""
    from avatarctl.viewer.server import ViewerServer, import_viser

    try:
        import_viser()
    except ImportError:
        raise InputError("the viewer needs the `viser` package", where="avatarctl[view]",
                         fix="pip install 'avatarctl[view]'") from None
    setup = prepare(project_dir, cfg)
    resolution = cfg.resolution or (512 if setup.avatar.device.type == "cuda" else 256)
    try:
        server = ViewerServer(setup.session, setup.initial, host=cfg.host, port=cfg.port, resolution=resolution,
                              preview_scale=cfg.preview_scale, settle_s=cfg.settle_s, fps=cfg.fps, latent=cfg.latent)
    except OSError as e:
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
    return {"url": server.url, "frames": len(setup.session.frames), "config": asdict(cfg),
            "background": list(np.asarray(setup.avatar.background, float))}
