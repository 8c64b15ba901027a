"""Realistically wrong body fits: `perturb_motion` adds per-frame noise to a motion's joint rotations and root
translation, the way real multi-view fits are off (a few degrees per joint, centimetres at the extremities, jitter
from frame to frame). Used by `avatarctl synth --fit-noise` to measure pose refinement against the true fits.

Each rotated joint gets, independently per frame, a rotation about a uniformly random axis by an angle drawn from
N(0, rot_deg^2) (composed in the joint's own frame); the root translation gets N(0, (transl_cm / 100)^2) per axis.
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


def perturb_motion(motion: BodyMotion, rot_deg: float, transl_cm: float, seed: int = 0) -> BodyMotion:
    """A copy of `motion` with per-frame noise on every joint rotation and on the root translation."""
    if rot_deg < 0 or transl_cm < 0:
        raise ValueError(f"noise must be >= 0, got {rot_deg} deg / {transl_cm} cm")
    rng = np.random.default_rng(seed)
    sigma, t_sigma = np.deg2rad(rot_deg), transl_cm / 100.0
    F = motion.num_frames
    if motion.body_model == "anny":
        P = motion.pose_parameters.astype(np.float64).copy()  # [F, J, 4, 4] local deltas; root: world pose
        P[:, :, :3, :3] = P[:, :, :3, :3] @ _random_rotations(rng, P.shape[:2], sigma)
        P[:, _ANNY_ROOT, :3, 3] += rng.normal(scale=t_sigma, size=(F, 3))
        return replace(motion, pose_parameters=P.astype(np.float32))
    J = motion.body_pose.shape[1] // 3
    body = _perturb_axis_angle(motion.body_pose.reshape(F, J, 3), _random_rotations(rng, (F, J), sigma))
    orient = _perturb_axis_angle(motion.global_orient, _random_rotations(rng, (F,), sigma))
    transl = motion.transl + rng.normal(scale=t_sigma, size=(F, 3)).astype(np.float32)
    return replace(motion, body_pose=body.reshape(F, J * 3), global_orient=orient, transl=transl)
