"""The capture's held-out frames posed by the fitted avatar's silhouette (issue 51 item 4; deviation `held_out_poses`).

Where the body fits are estimated (`model.pose_refine` on: keypoint fits, a phone video), a frame the avatar never
trained on keeps ingest's estimated pose, off by a limb's width on a phone video: its plain figure then mixes that
pose error with the avatar's. The fit corrects the training frames' poses with the avatar (model/pose_refine.py); it
learns nothing for the others. So, after training, the fit poses each test frame (`split.test_frames` that are not
training frames) the way `eval --refine-pose-from masks` does (fit/frame_pose.py: the avatar frozen, the joints of
`model.pose_refine` and the root, Adam, mean |alpha - mask| of the avatar's silhouette, clothes and hair included,
against the frame's masks, the first half of the steps at half size, a frame whose loss does not drop keeps its
pose), against the masks of the **training views** only (a held-out view's images are the test's ground truth; a
phone video has one view, the one ingest's keypoint fit already read). Each view is the bbox protocol's crop around
the estimated body. The colours of the test frames are never read.

The result is `fit/held_out_poses.npz` (`HeldOutPoses`: per frame the corrections delta [J, 3], tau [3] of
`frame_pose.refine_frame_pose` and the losses before and after, the checkpoint step the avatar was frozen at), valid
for that checkpoint only: a fit that runs again removes it first. `eval` and `render` drive a test frame with its
corrected joint transforms (`HeldOutPoses.joint_transforms`) when the file matches the checkpoint they load, and name
it (`eval --held-out-poses ingest` scores ingest's poses). It costs `steps` renders of every training view per test
frame after the training budget (synth `phone`: 17 frames x 1 view of 288 x 512, 80 steps, ~90 s on 2 cores). The
frames are posed in time order. From one training view (a video), each starts from the corrections of the frame
before it and keeps the best of ingest's pose, that start and where Adam ends: one silhouette leaves the pose
loosely held, and a neighbour's error is much like the frame's own (synth `phone` seeds 0 / 1: +0.34 / +0.55 dB over
starting at ingest's pose); from three views it cost synth `realistic` (6 fps) −0.25 / −0.11 / 0.00 dB, so there
each frame starts at ingest's pose (`WARM_START_MAX_VIEWS`). With a time budget the pass takes at most as long
again: the frames it has no time for keep ingest's poses (`held_out` says how many there were).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from avatarctl.atomic import atomic_path

if TYPE_CHECKING:
    from avatarctl.body.base import BodyModel, BodyTemplate
    from avatarctl.io.project_io import ProjectCapture
    from avatarctl.model.avatar import SlrfAvatar
    from avatarctl.progress import ProgressFn

FILE_NAME = "held_out_poses.npz"
WARM_START_MAX_VIEWS = 1  # up to this many training views a frame starts from the frame before's corrections
BBOX_PAD = 0.05  # metres the posed body's box is grown by for each view's crop (the bbox protocol's Neural Body pad)
PROTOCOL = ("the capture's test frames posed by the fit: ingest's estimated pose refined against the training views' "
            "masks with the avatar frozen (fit/held_out_poses.py: the avatar's silhouette, mean |alpha - mask|); the "
            "frames' colours are not read")


@dataclass(frozen=True)
class HeldOutPoses:
    """The fit's pose corrections of the capture's test frames (module docstring); rows follow `frames`."""

    frames: tuple[int, ...]  # [F] capture frame numbers
    delta: np.ndarray  # [F, J, 3] axis-angle joint corrections, radians (0 for joints not refined)
    tau: np.ndarray  # [F, 3] root translation, metres
    loss_start: np.ndarray  # [F] mean |alpha - mask| at the estimated pose (full size)
    loss_end: np.ndarray  # [F] at the corrected pose (= loss_start where the frame kept its pose)
    step: int  # the checkpoint step of the frozen avatar
    steps: int  # Adam steps per frame
    views: tuple[str, ...]  # the training views whose masks were fitted
    seconds: float
    held_out: int  # the capture's held-out frames (> len(frames) when the pass stopped at its time limit)

    def __contains__(self, frame: int) -> bool:
        return int(frame) in self.frames

    def joint_transforms(self, model: "SlrfAvatar", template: "BodyTemplate", frame: int, M: torch.Tensor
                         ) -> torch.Tensor:
        """[1, J, 4, 4] M'_j = D_j M_j of test frame `frame` from its estimated `M` [1, J, 4, 4]
        (`frame_pose.corrected_joints`)."""
        from avatarctl.fit.frame_pose import corrected_joints

        i = self.frames.index(int(frame))
        return corrected_joints(model, template, M, torch.from_numpy(self.delta[i]), torch.from_numpy(self.tau[i]))

    def summary(self) -> dict[str, object]:
        """What the pass did, for the fit's record and table."""
        moved = self.loss_end < self.loss_start
        ang = np.degrees(np.linalg.norm(self.delta, axis=-1).max(axis=-1)) if len(self.frames) else np.zeros(0)
        shift = np.linalg.norm(self.tau, axis=-1) * 100 if len(self.frames) else np.zeros(0)
        return {"frames": len(self.frames), "held_out": self.held_out, "moved": int(moved.sum()),
                "views": list(self.views), "steps": self.steps,
                "mask_loss_before": round(float(self.loss_start.mean()), 5) if len(self.frames) else None,
                "mask_loss_after": round(float(self.loss_end.mean()), 5) if len(self.frames) else None,
                "max_angle_deg_mean": round(float(ang.mean()), 3) if len(ang) else 0.0,
                "root_shift_cm_mean": round(float(shift.mean()), 3) if len(shift) else 0.0,
                "seconds": round(self.seconds, 1), "checkpoint_step": self.step}

    def save(self, path: Path) -> None:
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as fh:
                np.savez(fh, frames=np.asarray(self.frames, np.int64), delta=self.delta.astype(np.float32),
                         tau=self.tau.astype(np.float32), loss_start=self.loss_start.astype(np.float64),
                         loss_end=self.loss_end.astype(np.float64), step=np.int64(self.step),
                         steps=np.int64(self.steps), views=np.asarray(self.views, str),
                         seconds=np.float64(self.seconds), held_out=np.int64(self.held_out),
                         protocol=np.asarray(PROTOCOL))

    @classmethod
    def load(cls, path: Path) -> "HeldOutPoses":
        with np.load(path, allow_pickle=False) as z:
            return cls(frames=tuple(int(f) for f in z["frames"]), delta=z["delta"].astype(np.float32),
                       tau=z["tau"].astype(np.float32), loss_start=z["loss_start"], loss_end=z["loss_end"],
                       step=int(z["step"]), steps=int(z["steps"]), views=tuple(str(v) for v in z["views"]),
                       seconds=float(z["seconds"]), held_out=int(z["held_out"]))


def held_out_frames(capture: "ProjectCapture", train_frames: list[int]) -> list[int]:
    """The capture's test frames the avatar did not train on (the `novel_pose` split's frames)."""
    trained = {int(f) for f in train_frames}
    return sorted({int(f) for f in capture.split.test_frames} - trained)


def pose_held_out_frames(model: "SlrfAvatar", template: "BodyTemplate", body: "BodyModel", capture: "ProjectCapture",
                         train_frames: list[int], background: tuple[float, float, float], step: int, steps: int,
                         progress: "ProgressFn | None" = None, limit_s: float | None = None) -> HeldOutPoses:
    """Pose the held-out frames against the training views' masks (module docstring), in time order, each started
    from the corrections of the frame before it up to `WARM_START_MAX_VIEWS` training views; with `limit_s`, no frame
    is started that the mean time per frame so far says would end past it (the later ones keep ingest's poses). The
    model is left as it was."""
    from avatarctl.fit.conditioning import conditioning_for_motion
    from avatarctl.fit.frame_pose import FramePoseConfig, crop_views, refine_frame_pose
    from avatarctl.progress import ProgressReport

    t0 = time.perf_counter()
    frames = held_out_frames(capture, train_frames)
    views = list(capture.split.train_views)
    warm = len(views) <= WARM_START_MAX_VIEWS
    dev = model.node_rest.device
    bg = torch.tensor(background, dtype=torch.float32)
    cfg = FramePoseConfig(steps=steps, target="masks")
    cams = {v: capture.cameras[v].pinhole() for v in views}
    J = len(template.parents)
    delta = np.zeros((len(frames), J, 3), np.float32)
    tau = np.zeros((len(frames), 3), np.float32)
    start, end = np.zeros(len(frames)), np.zeros(len(frames))
    motion = capture.motion.for_frames(frames)
    was_training = model.training
    model.eval()
    done = 0
    try:
        for i, frame in enumerate(frames):
            spent = time.perf_counter() - t0
            if limit_s is not None and i and spent + spent / i > limit_s:
                break
            one = motion.select([i])
            with torch.no_grad():
                verts = body.pose(one).vertices[0].detach().float().cpu().numpy()
            pose_views = crop_views(capture, frame, views, cams, verts, background, dev, pad=BBOX_PAD, images=False)
            cond = conditioning_for_motion(body, one, train_frames, False, dev)
            pose = refine_frame_pose(model, template, cond, pose_views, bg, "novel", cfg,
                                     start_from=(delta[i - 1], tau[i - 1]) if i and warm else None)
            delta[i], tau[i], start[i], end[i] = pose.delta, pose.tau, pose.loss_start, pose.loss_end
            done = i + 1
            if progress is not None:
                progress(ProgressReport(done=done, total=len(frames), part="held-out poses"))
    finally:
        model.train(was_training)
    return HeldOutPoses(frames=tuple(frames[:done]), delta=delta[:done], tau=tau[:done], loss_start=start[:done],
                        loss_end=end[:done], step=int(step), steps=steps, views=tuple(views),
                        seconds=time.perf_counter() - t0, held_out=len(frames))


def load_held_out_poses(fit_dir: Path, step: int) -> tuple["HeldOutPoses | None", str | None]:
    """(the fit's test poses, None) when `fit_dir` holds them for checkpoint `step`; (None, why not) when it holds
    them for another checkpoint or cannot read them; (None, None) when there are none."""
    path = Path(fit_dir) / FILE_NAME
    if not path.is_file():
        return None, None
    try:
        poses = HeldOutPoses.load(path)
    except (OSError, ValueError, KeyError) as e:
        return None, f"{path} unreadable ({type(e).__name__}): the test frames keep ingest's poses"
    if poses.step != int(step):
        return None, (f"{path} was written for checkpoint step {poses.step}, not {step}: the test frames keep "
                      f"ingest's poses (fit again, or load that checkpoint)")
    return poses, None


def remove_held_out_poses(fit_dir: Path) -> None:
    """A fit that runs again makes the file stale (module docstring)."""
    (Path(fit_dir) / FILE_NAME).unlink(missing_ok=True)
