"""What several stages share, stated once: view / latent selection, the sample-seed formula, the cheap pre-checks,
loading a fitted avatar, making a motion file (`--poses`) drive it, running a stage on several ranks (`run_ranked`)
and holding the lock of what a stage writes (`writing`).

The progress report is `avatarctl.progress` (libraries send it too); comma lists are `avatarctl.lists`; frame specs
are `avatarctl.frames` (ingest uses them too); ground-truth compositing is `avatarctl.evaluate.protocols.ground_truth`
(fit targets and validation use it too); devices are `avatarctl.device.resolve_device` (the fit loop uses it too).
"""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Iterator

from avatarctl.errors import InputError
from avatarctl.lists import split_list
from avatarctl.progress import ProgressFn

if TYPE_CHECKING:
    from avatarctl.body.motion import BodyMotion
    from avatarctl.fit.checkpoint import LoadedAvatar
    from avatarctl.fit.held_out_poses import HeldOutPoses
    from avatarctl.geometry.cameras import Camera
    from avatarctl.model.avatar import FrameConditioning, NodeState
    from avatarctl.project import Project

def quiet_kernels(quiet: bool) -> None:
    """Whether Warp is initialised quietly in this process (`device.init_warp`: no banner, no per-module lines, no
    missing-driver warning); the CLI asks for it unless debugging."""
    import os

    from avatarctl.device import WARP_QUIET_ENV

    os.environ[WARP_QUIET_ENV] = "1" if quiet else "0"


LATENT_MODES = ("auto", "mean", "zero", "sample")
KNOCKOUTS = ("delta-n", "embedding")
"""Render-time knockouts of a trained model (`render` / `eval --knockout`): that variable is set to zero when
rendering (the paper's Fig. 3 and supp. Tab. B, the node-variable knock-out)."""


def check_latent_mode(mode: str) -> None:
    if mode not in LATENT_MODES:
        raise InputError(f"unknown latent mode {mode!r}", where="--latent",
                         fix=f"use one of: {', '.join(LATENT_MODES)}")


def check_knockout(knockout: tuple[str, ...]) -> tuple[str, ...]:
    """`knockout` validated (each in KNOCKOUTS, no repeats) in KNOCKOUTS order."""
    bad = [k for k in knockout if k not in KNOCKOUTS]
    if bad:
        raise InputError(f"unknown knockout {bad}", where="--knockout", fix=f"use: {', '.join(KNOCKOUTS)}")
    return tuple(k for k in KNOCKOUTS if k in knockout)


def parse_knockout(spec: str | None) -> tuple[str, ...]:
    """'delta-n,embedding' (the CLI's comma list) -> ("delta-n", "embedding"); None or '' -> ()."""
    return split_list(spec)


def knocked_out(avatar: "LoadedAvatar", state: "NodeState", knockout: tuple[str, ...]) -> "NodeState":
    """`state` with the `knockout` variables zeroed (`SlrfAvatar.knock_out`); `state` itself when none."""
    if not knockout:
        return state
    return avatar.model.knock_out(state, delta_n="delta-n" in knockout, embedding="embedding" in knockout)


def latent_for(mode: str, is_training: bool) -> str:
    """The latent of one frame: "auto" = the posterior mean z = mu for training frames, the model's novel-pose latent
    for novel ones ("novel": z = 0 as in paper Sec. 4.1, or the training mean with `model.novel_latent`); "mean"
    needs a training frame (mu comes from the cVAE encoder of its time stamp)."""
    if mode == "auto":
        return "mean" if is_training else "novel"
    if mode == "mean" and not is_training:
        raise InputError("--latent mean needs training frames (z = mu comes from the cVAE encoder of a training "
                         "frame's time stamp)", where="--latent",
                         fix="use --latent zero or sample for novel poses, or training frames")
    return mode


def sample_seed(seed: int, frame: int) -> int:
    """The seed of the latent sample of one frame (`--latent sample --seed N`): the same image for the same frame."""
    return int(seed) * 1_000_003 + int(frame)


def frame_conditioning(avatar: "LoadedAvatar", one: "BodyMotion", frame: int, is_training: bool,
                       held_out: "HeldOutPoses | None" = None) -> "FrameConditioning":
    """The conditioning of one frame (`one`: a motion of one row); a held-out frame of the capture that the fit posed
    (`held_out`, fit/held_out_poses.py; None: none) is driven by its corrected joint transforms."""
    from dataclasses import replace

    cond = avatar.conditioning(one, frames_are_training=is_training)
    if held_out is not None and not is_training and frame in held_out:
        cond = replace(cond, joint_transforms=held_out.joint_transforms(avatar.model, avatar.template, frame,
                                                                        cond.joint_transforms))
    return cond


def fitted_held_out_poses(avatar: "LoadedAvatar") -> "HeldOutPoses | None":
    """The fit's poses of the capture's held-out frames (fit/held_out_poses.py) when the fit wrote them for the
    checkpoint `avatar` was loaded from; else None (those frames keep ingest's poses)."""
    from avatarctl.fit.held_out_poses import load_held_out_poses

    return load_held_out_poses(avatar.capture.project.paths.fit, avatar.step)[0]


def frame_node_state(avatar: "LoadedAvatar", one: "BodyMotion", frame: int, is_training: bool, latent: str,
                     seed: int, held_out: "HeldOutPoses | None" = None) -> "NodeState":
    """NodeState of one frame (`one`: a motion of one row) with latent mode `latent` (mean | zero | sample);
    `held_out`: `frame_conditioning`'s."""
    import torch

    cond = frame_conditioning(avatar, one, frame, is_training, held_out)
    gen = torch.Generator(device=avatar.device).manual_seed(sample_seed(seed, frame)) if latent == "sample" else None
    with torch.no_grad():
        return avatar.model.node_state(cond, mode=latent, generator=gen)


def motion_for_avatar(avatar: "LoadedAvatar", path: str | Path, recenter: bool) -> tuple["BodyMotion", str | None]:
    """A motion file (`--poses`) made ready to drive `avatar` -> (motion, what retargeting did or None).

    Any rig `io.motion_files.read_motion` reads: a motion made for the avatar's body model is used as it is (anny
    bone labels checked), another is retargeted onto it (`io.motion_convert`, with the project's SMPL / SMPL-X model
    file); the subject's shape is replaced by the avatar's own (`adopt_subject`) and, with `recenter`, the motion is
    translated so its first frame starts where the avatar's first training frame stands."""
    from avatarctl.io import motion_files

    cap = avatar.capture
    retarget: str | None = None
    inp = motion_files.read_motion(path)
    if inp.family == cap.body_model and inp.body is not None:
        motion = inp.body
        if motion.body_model == "anny":
            motion_files.check_joint_labels(path, avatar.template.joint_names)
    else:  # another rig: retarget onto the avatar's body model, its own subject, its model file
        from avatarctl.io.motion_convert import convert_motion

        conv = convert_motion(inp, cap.body_model, subject=cap.motion, model_path=cap.body_model_path)
        motion = conv.motion
        retarget = conv.summary(inp.kind)
    motion = motion_files.adopt_subject(motion, cap.motion)
    if recenter:
        train = [int(f) for f in avatar.train_frames]
        anchor_row = cap.motion.rows_for([min(train) if train else cap.frames[0]])
        anchor = motion_files.root_translation(cap.motion.select(anchor_row))[0]
        motion = motion_files.shift_motion(motion, anchor - motion_files.root_translation(motion)[0])
    return motion, retarget


def select_views(names: tuple[str, ...], cameras: dict[str, "Camera"], what: str = "--views") -> list[str]:
    """Check capture camera names (in the order given, duplicates dropped)."""
    unknown = [n for n in names if n not in cameras]
    if unknown:
        raise InputError(f"unknown camera(s) {unknown}", where=what, fix=f"choose among: {', '.join(cameras)}")
    return list(dict.fromkeys(names))


def precheck(project: "Project", checkpoint: str | None, views: tuple[str, ...]) -> None:
    """Cheap checks before the avatar is loaded (which takes seconds): the checkpoint file and the camera names."""
    if checkpoint is not None and not Path(checkpoint).is_file():
        raise InputError("checkpoint file not found", where=str(checkpoint), fix="check the --checkpoint path")
    if views:
        from avatarctl.io.project_io import load_cameras

        select_views(views, load_cameras(project.paths.cameras))


def open_fitted(project_dir: "str | Path", checkpoint: str | None, views: tuple[str, ...] = (),
                poses: str | None = None) -> "Project":
    """The project of a stage that needs a fit, with the cheap checks done (fit recorded, checkpoint file, camera
    names, motion file present) before the avatar is loaded."""
    from avatarctl.project import Project

    project = Project.open(project_dir)
    project.require("fit")
    if poses is not None and not Path(poses).is_file():
        raise InputError("motion file not found", where=str(poses), fix="check the --poses path")
    precheck(project, checkpoint, views)
    return project


def load_fitted(project: "Project", device: str, checkpoint: str | None) -> "LoadedAvatar":
    """The project's fitted avatar (`checkpoint`, default the latest) on the resolved `device`, in eval mode."""
    from avatarctl.device import resolve_device
    from avatarctl.fit.checkpoint import load_avatar

    ckpt = Path(checkpoint) if checkpoint else None
    return load_avatar(project, device=str(resolve_device(device)), checkpoint=ckpt)


def run_ranked(stage: Callable[..., Any], nproc: int, args: tuple, progress: ProgressFn | None, device: str,
               what: str) -> Any:
    """Run `stage(env, progress, *args)` on ranks (render and eval; fit has its own, with a stop protocol):
    `nproc > 1` spawns them here (`dist.launch`, rank 0's progress and result come back); in a torchrun launch
    this process is one of them; else `env` is None (one process). `stage` must be a module-level function."""
    from avatarctl.device import resolve_device
    from avatarctl.dist import DistEnv, launch, process_group

    if nproc < 1:
        raise InputError(f"--nproc must be >= 1, got {nproc}", where="--nproc", fix="e.g. --nproc 2")
    env = DistEnv.from_env()
    if nproc > 1:
        if env is not None:
            raise InputError("--nproc inside a torchrun launch", where="--nproc",
                             fix="let torchrun start the ranks (--nproc_per_node) and drop --nproc")
        return launch(_ranked, nproc, (stage, device, args), on_progress=progress, what=what,
                      fix="nothing was written (outputs are renamed into place only when complete); re-run")
    if env is None:
        return stage(None, progress, *args)
    with process_group(env, resolve_device(device)):
        return stage(env, progress if env.is_main else None, *args)


def _ranked(env: Any, channel: Any, stage: Callable[..., Any], device: str, args: tuple) -> Any:
    """A rank spawned by `run_ranked`: join the group and run the stage, rank 0 sending its progress back."""
    from avatarctl.device import resolve_device
    from avatarctl.dist import process_group

    with process_group(env, resolve_device(device)):
        return stage(env, channel.send_progress if env.is_main else None, *args)


def rank_device_name(env: Any, device: str) -> str:
    """`--device` for this rank: cuda:LOCAL_RANK on a CUDA run of several ranks, else the option's device."""
    from avatarctl.device import resolve_device
    from avatarctl.dist import rank_device

    return str(rank_device(env, resolve_device(device)))


@contextlib.contextmanager
def writing(dest: Path, command: str, wait: bool, sweep: bool = False) -> Iterator[bool]:
    """Hold the lock of the output `dest` (`avatarctl.lock.hold`) while the stage runs; yields whether this process
    holds it. Under torchrun only rank 0 takes it (the ranks > 0 yield False); the ranks of `--nproc` are spawned
    by the process that holds it. `sweep`: also tidy what killed writers left of the other outputs in `dest`'s
    folder (render/, eval/, export/)."""
    from avatarctl.dist import DistEnv
    from avatarctl.lock import hold, sweep as sweep_folder

    env = DistEnv.from_env()
    if env is not None and not env.is_main:
        yield False
        return
    with hold(dest, command, wait=wait):
        if sweep:
            sweep_folder(dest.parent)
        yield True
