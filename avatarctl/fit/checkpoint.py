"""Checkpoint files and `load_avatar`, the one way render / eval get a fitted avatar back.

A checkpoint is `torch.save` of a plain dict of tensors and JSON-able values (nothing pickled but those; it loads
with `torch.load(weights_only=True)`):

    format            "avatarctl.fit.checkpoint"
    schema_version    1
    step              int, optimisation steps completed
    model             SlrfAvatar.state_dict()
    optimizer         Adam state_dict
    scheduler         LambdaLR state_dict
    rng               {"torch": ByteTensor, "cuda": [ByteTensor], "sampler": ByteTensor, "noise": ByteTensor}
                      (shard 0's generators), with S > 1 ray shards also "sampler_shards", "noise_shards":
                      ByteTensor [S, state bytes] (fit/distributed.py)
    model_config      ModelConfig.to_json()
    fit_config        FitConfig.to_json()
    train_frames      [int], capture frame numbers the model was trained on, in time-stamp order
    avatarctl_version str

Files are written atomically and durably (temporary file, fsync, rename, folder fsync: `atomic.atomic_path`):
`fit/checkpoints/step_<step:08d>.pt`, then `latest.pt`; older step files are deleted only after both.
"""

from __future__ import annotations

import contextlib
import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch

from avatarctl import __version__
from avatarctl.atomic import atomic_path
from avatarctl.body.base import BodyModel, BodyTemplate
from avatarctl.body.motion import BodyMotion
from avatarctl.errors import InputError, ProjectError
from avatarctl.io.project_io import ProjectCapture
from avatarctl.project import Project

if TYPE_CHECKING:
    from avatarctl.fit.config import FitConfig
    from avatarctl.model.avatar import FrameConditioning, SlrfAvatar
    from avatarctl.model.config import ModelConfig

FORMAT = "avatarctl.fit.checkpoint"
SCHEMA_VERSION = 1


def _torch_save(obj: dict[str, Any], dest: Path) -> None:
    """`torch.save` through a Python file object, so that a refused write (disk full, quota, file-size limit)
    surfaces as that `OSError` with its errno: torch's own writer reports it as a RuntimeError ("file write
    failed" / "unexpected pos") and the CLI could not tell a full disk from a bug."""
    with open(dest, "wb") as fh:
        try:
            torch.save(obj, fh)
        except RuntimeError as e:
            if isinstance(e.__context__, OSError):
                raise e.__context__ from None
            raise


def save_checkpoint(project: Project, payload: dict[str, Any], keep: int = 3) -> Path:
    """Write `payload` (see the module docstring) as `step_<step>.pt` and `latest.pt`, atomically and durably;
    then keep the `keep` most recent step files. Returns the step file."""
    paths = project.paths
    step = int(payload["step"])
    payload = {"format": FORMAT, "schema_version": SCHEMA_VERSION, "avatarctl_version": __version__, **payload}
    dest = paths.checkpoint(step)
    with atomic_path(dest) as tmp:
        _torch_save(payload, tmp)
    # latest.pt: a hard link to the step file when the file system allows it, else a copy; renamed into place.
    with atomic_path(paths.latest_checkpoint) as tmp:
        tmp.unlink()
        try:
            os.link(dest, tmp)
        except OSError:
            _torch_save(payload, tmp)
    step_files = sorted(paths.checkpoints.glob("step_*.pt"))
    for old in step_files[:-keep] if keep > 0 else []:
        with contextlib.suppress(FileNotFoundError):
            old.unlink()
    return dest


def save_snapshot(project: Project, payload: dict[str, Any], seconds: float) -> Path:
    """Write `payload` as `checkpoints/snapshot_<seconds>s.pt` (atomic; never pruned, never `latest`): the state
    after that much training time, for quality-versus-time benchmarks (`FitConfig.snapshot_at_s`)."""
    payload = {"format": FORMAT, "schema_version": SCHEMA_VERSION, "avatarctl_version": __version__, **payload}
    dest = project.paths.checkpoints / f"snapshot_{int(round(seconds)):05d}s.pt"
    with atomic_path(dest) as tmp:
        _torch_save(payload, tmp)
    return dest


def read_checkpoint(path: Path, device: str | torch.device = "cpu") -> dict[str, Any]:
    """Load a checkpoint dict (tensors mapped to `device`); a clear `ProjectError` when missing or foreign."""
    path = Path(path)
    if not path.is_file():
        raise ProjectError("fit checkpoint not found", where=str(path),
                           fix="run `avatarctl fit PROJECT` (or pass an existing checkpoint file)")
    try:
        ckpt = torch.load(path, map_location=device, weights_only=True)
    except Exception as e:  # corrupt file, foreign pickle, truncated download, empty file
        detail = " ".join(str(e).split())[:120] or "empty or cut-off file"
        raise ProjectError(f"cannot read fit checkpoint ({type(e).__name__}: {detail})",
                           where=str(path), fix="use another checkpoint or re-run `avatarctl fit`") from None
    if not isinstance(ckpt, dict) or ckpt.get("format") != FORMAT:
        raise ProjectError("not an avatarctl fit checkpoint", where=str(path), fix="pass a file from fit/checkpoints/")
    if ckpt.get("schema_version") != SCHEMA_VERSION:
        raise ProjectError(f"unsupported checkpoint schema_version {ckpt.get('schema_version')!r}", where=str(path),
                           fix="use the avatarctl version that wrote it, or re-run `avatarctl fit`")
    return ckpt


@dataclass
class LoadedAvatar:
    """A fitted avatar with everything needed to render it (model in eval mode on its device)."""

    model: "SlrfAvatar"
    model_config: "ModelConfig"
    fit_config: "FitConfig"  # the config the avatar was trained with (background, seed, ablations, ...)
    step: int  # optimisation steps the checkpoint holds
    template: BodyTemplate
    body: BodyModel
    capture: ProjectCapture  # avatarctl.io.project_io.load_project_capture(project)
    train_frames: list[int]  # capture frame numbers the model was trained on, in time-stamp order
    checkpoint: Path | None = None  # the file it came from

    @property
    def background(self) -> tuple[float, float, float]:
        """The colour the avatar was trained (and should be rendered / scored) over."""
        return self.fit_config.background

    @property
    def device(self) -> torch.device:
        return next(self.model.parameters()).device

    def conditioning(self, motion: BodyMotion, frames_are_training: bool) -> "FrameConditioning":
        """Conditioning for every row of `motion`: joint transforms and pose features from the body model; time
        stamp t/T and frame id t for training frames (every frame must be one), 0 and -1 for novel frames."""
        from avatarctl.fit.conditioning import conditioning_for_motion

        return conditioning_for_motion(self.body, motion, self.train_frames, frames_are_training, self.device)


def saved_configs(ckpt: dict[str, Any], path: Path) -> tuple["FitConfig", "ModelConfig"]:
    """(fit config, model config) a checkpoint was trained with; a one-line `ProjectError` when they hold settings
    this avatarctl does not read (a checkpoint of another version), not an internal error."""
    from avatarctl.fit.config import FitConfig
    from avatarctl.model.config import ModelConfig

    try:
        return FitConfig.from_json(ckpt["fit_config"]), ModelConfig.from_json(ckpt["model_config"])
    except (InputError, ValueError, TypeError) as e:
        what = e.what if isinstance(e, InputError) else str(e)
        raise ProjectError(f"the checkpoint's settings are not ones this avatarctl reads ({what})", where=str(path),
                           fix="it was written by another avatarctl version: use that version, or start over with "
                               "`avatarctl fit --fresh`") from None


def load_avatar(project: Project, device: str = "cpu", checkpoint: Path | None = None) -> LoadedAvatar:
    """Rebuild the fitted avatar from `checkpoint` (default: the project's latest) on `device`, in eval mode."""
    from avatarctl.body.registry import load_body_model
    from avatarctl.io.project_io import load_project_capture
    from avatarctl.model.avatar import SlrfAvatar

    path = Path(checkpoint) if checkpoint is not None else project.paths.latest_checkpoint
    ckpt = read_checkpoint(path, device="cpu")
    fit_cfg, cfg = saved_configs(ckpt, path)
    capture = load_project_capture(project)
    body = load_body_model(capture.body_model, capture.body_model_path)
    template = body.template(capture.motion)
    train_frames = [int(f) for f in ckpt["train_frames"]]
    cameras = tuple(ckpt["colour_cameras"]) if cfg.colour.enabled else ()  # the transforms' training cameras
    model = SlrfAvatar(cfg, template, num_frames=len(train_frames), seed=fit_cfg.seed, cameras=cameras)
    try:
        model.load_state_dict(ckpt["model"])
    except RuntimeError as e:
        raise ProjectError(f"checkpoint does not match this project's body/template ({str(e).splitlines()[0]})",
                           where=str(path), fix="re-run `avatarctl fit` on this project") from None
    model.to(device).eval()
    return LoadedAvatar(model=model, model_config=cfg, fit_config=fit_cfg, step=int(ckpt["step"]), template=template,
                        body=body, capture=capture, train_frames=train_frames, checkpoint=path)
