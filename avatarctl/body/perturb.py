"""Realistically wrong body fits: `perturb_motion` adds per-frame noise to a motion's joint rotations and root
translation, the way real multi-view fits are off (a few degrees per joint, centimetres at the extremities, jitter
from frame to frame). Used by `avatarctl synth --fit-noise` to measure pose refinement against the true fits.

Each rotated joint gets, independently per frame, a rotation about a uniformly random axis by an angle drawn from
N(0, rot_deg^2) (composed in the joint's own frame); the root translation gets N(0, (transl_cm / 100)^2) per axis.

With `corr_frames` > 0 the errors drift instead of jittering: every component of the noise (axis-angle vector,
translation) is white noise smoothed over time by a Gaussian of `corr_frames` frames and rescaled to the same RMS
(rot_deg for the rotation angle, transl_cm per translation axis), so neighbouring frames are off in the same way, as
fits that lose track of a limb for a while are. Temporal smoothing cannot remove such errors; only the images can.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from avatarctl.body.motion import BodyMotion

_ANNY_ROOT = 0  # anny's bone 0 is `root`; its delta is the root's world pose (synth.motion)


def _random_rotations(rng: np.random.Generator, shape: tuple[int, ...], sigma_rad: float) -> np.ndarray:
    """[*shape, 3, 3] rotations about random axes by N(0, sigma^2) angles."""
    from scipy.spatial.transform import Rotation

    axis = rng.normal(size=shape + (3,))
    axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
    angle = rng.normal(scale=sigma_rad, size=shape)[..., None]
    return Rotation.from_rotvec((axis * angle).reshape(-1, 3)).as_matrix().reshape(shape + (3, 3))


def _perturb_axis_angle(aa: np.ndarray, noise: np.ndarray) -> np.ndarray:
    """[..., 3] axis-angle composed with [..., 3, 3] noise rotations (in the joint frame) -> [..., 3]."""
    from scipy.spatial.transform import Rotation

    flat = aa.reshape(-1, 3).astype(np.float64)
    out = (Rotation.from_rotvec(flat) * Rotation.from_matrix(noise.reshape(-1, 3, 3))).as_rotvec()
    return out.reshape(aa.shape).astype(np.float32)


def _drifting(rng: np.random.Generator, shape: tuple[int, ...], scale: float, corr_frames: float) -> np.ndarray:
    """[F, ...] Gaussian noise smoothed along axis 0 (frames) by a Gaussian of `corr_frames`, RMS `scale` per
    component."""
    from scipy.ndimage import gaussian_filter1d

    radius = int(4.0 * corr_frames + 0.5)  # scipy's truncation at 4 sigma
    kernel = np.exp(-0.5 * (np.arange(-radius, radius + 1) / corr_frames) ** 2)
    kernel /= kernel.sum()  # the filter: white noise of RMS 1 comes out with RMS |kernel|
    smooth = gaussian_filter1d(rng.normal(size=shape), corr_frames, axis=0, mode="wrap")
    return smooth * (scale / np.sqrt((kernel ** 2).sum()))


def _drifting_rotations(rng: np.random.Generator, shape: tuple[int, ...], sigma_rad: float,
                        corr_frames: float) -> np.ndarray:
    """[*shape, 3, 3] rotations whose axis-angle vectors drift over axis 0; RMS angle sigma_rad."""
    from scipy.spatial.transform import Rotation

    rotvec = _drifting(rng, shape + (3,), sigma_rad / np.sqrt(3.0), corr_frames)
    return Rotation.from_rotvec(rotvec.reshape(-1, 3)).as_matrix().reshape(shape + (3, 3))


def perturb_motion(motion: BodyMotion, rot_deg: float, transl_cm: float, seed: int = 0,
                   corr_frames: float = 0.0) -> BodyMotion:
    """A copy of `motion` with noise on every joint rotation and on the root translation: independent per frame
    (corr_frames = 0), or drifting over about `corr_frames` frames (module docstring)."""
    if rot_deg < 0 or transl_cm < 0 or corr_frames < 0:
        raise ValueError(f"noise must be >= 0, got {rot_deg} deg / {transl_cm} cm / {corr_frames} frames")
    rng = np.random.default_rng(seed)
    sigma, t_sigma = np.deg2rad(rot_deg), transl_cm / 100.0
    F = motion.num_frames

    def rotations(shape: tuple[int, ...]) -> np.ndarray:
        return (_drifting_rotations(rng, shape, sigma, corr_frames) if corr_frames > 0
                else _random_rotations(rng, shape, sigma))

    def translations() -> np.ndarray:
        if corr_frames > 0:
            return _drifting(rng, (F, 3), t_sigma, corr_frames)
        return rng.normal(scale=t_sigma, size=(F, 3))

    if motion.body_model == "anny":
        P = motion.pose_parameters.astype(np.float64).copy()  # [F, J, 4, 4] local deltas; root: world pose
        P[:, :, :3, :3] = P[:, :, :3, :3] @ rotations(P.shape[:2])
        P[:, _ANNY_ROOT, :3, 3] += translations()
        return replace(motion, pose_parameters=P.astype(np.float32))
    J = motion.body_pose.shape[1] // 3
    body = _perturb_axis_angle(motion.body_pose.reshape(F, J, 3), rotations((F, J)))
    orient = _perturb_axis_angle(motion.global_orient, rotations((F,)))
    transl = motion.transl + translations().astype(np.float32)
    return replace(motion, body_pose=body.reshape(F, J * 3), global_orient=orient, transl=transl)
