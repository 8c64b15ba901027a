"""Body fits -> one internal `BodyMotion` per body model, and the sanity checks ingest applies to them.

The EasyMocap / ZJU-MoCap convention ``v = R(Rh) · SMPL(poses, shapes) + Th`` rotates about the world ORIGIN;
SMPL's ``global_orient`` rotates about the (shaped, rest) pelvis joint J0, then adds ``transl``:
``v = R_g · (x − J0) + J0 + transl`` for a point x rigidly attached to the root. Equating both:

    R_g    = R(Rh) · R(poses[:3])
    transl = Th + R(Rh) · J0 − J0
"""

from __future__ import annotations

import numpy as np

from avatarctl.body.motion import BodyMotion
from avatarctl.errors import InputError
from avatarctl.io.capture import BodyFits, RhThFits, fmt_list

MAX_METRES = 50.0  # a capture volume larger than this means the numbers are millimetres


def rhth_to_smpl(Rh: np.ndarray, Th: np.ndarray, root_pose: np.ndarray, J0: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """EasyMocap (Rh, Th) + SMPL root pose -> SMPL (global_orient, transl).

    Args:
        Rh: [frames, 3] axis-angle about the world origin. Th: [frames, 3] metres.
        root_pose: [frames, 3] SMPL root axis-angle (``poses[:, :3]``, rotation about the pelvis).
        J0: [3] shaped rest pelvis joint of the subject (metres, canonical frame).
    Returns:
        global_orient [frames, 3] axis-angle, transl [frames, 3] metres.
    """
    import torch

    from avatarctl.body.lbs import axis_angle_to_matrix, matrix_to_axis_angle

    R_h = axis_angle_to_matrix(torch.as_tensor(Rh, dtype=torch.float64))  # [frames, 3, 3]
    R_0 = axis_angle_to_matrix(torch.as_tensor(root_pose, dtype=torch.float64))  # [frames, 3, 3]
    go = matrix_to_axis_angle(R_h @ R_0).numpy()
    j0 = np.asarray(J0, dtype=np.float64).reshape(3)
    transl = np.asarray(Th, dtype=np.float64) + (R_h.numpy() @ j0) - j0
    return go, transl


def smpl_rest_pelvis(body, kind: str, betas: np.ndarray) -> np.ndarray:
    """[3] the shaped rest pelvis joint J0 of `body` (an SmplBody) for `betas` (zero pose, zero transl)."""
    dim = 69 if kind == "smpl" else 63
    zero = BodyMotion(body_model=kind, frame_index=np.zeros(1), global_orient=np.zeros((1, 3)),
                      body_pose=np.zeros((1, dim)), transl=np.zeros((1, 3)), betas=betas)
    return body.joints(zero)[0, 0].double().cpu().numpy()


def to_body_motion(fits: BodyFits, body_model_name: str, body, fps: float = 30.0) -> BodyMotion:
    """The capture's fits as a `BodyMotion` for `body_model_name` (no conversion between body models)."""
    if fits.body_model != body_model_name:
        where = fits.where if isinstance(fits, RhThFits) else None
        fix = ("use --body-model anny" if fits.body_model == "anny" else
               f"use --body-model {fits.body_model} --body-model-path /path/to/{fits.body_model.upper()}_NEUTRAL.pkl")
        raise InputError(f"the capture's fits are for {fits.body_model}, not {body_model_name}; avatarctl does not "
                         "convert between body models", where=where, fix=fix)
    if isinstance(fits, BodyMotion):
        return fits
    J0 = smpl_rest_pelvis(body, fits.kind, fits.shapes)
    go, transl = rhth_to_smpl(fits.Rh, fits.Th, fits.poses[:, :3], J0)
    return BodyMotion(body_model=fits.kind, frame_index=fits.frame_index, fps=fps, global_orient=go,
                      body_pose=fits.poses[:, 3:], transl=transl, betas=fits.shapes)


def with_hand_mean(motion: BodyMotion, hands_mean: np.ndarray | None, where: str) -> BodyMotion:
    """SMPL-X fits whose hand poses are offsets from the model's hand mean (smplx `flat_hand_mean=False`) -> full
    axis-angle hand poses (the project's convention): + `hands_mean` [90] (left 45, then right 45) of the model file."""
    from dataclasses import replace

    if motion.body_model != "smplx" or motion.left_hand_pose is None or motion.right_hand_pose is None:
        return motion
    if hands_mean is None:
        raise InputError("the capture's SMPL-X hand poses are offsets from the model's hand mean, and the model file "
                         "has no hands_meanl / hands_meanr", where=where,
                         fix="pass the SMPL-X model file of the smplx package (SMPLX_NEUTRAL.npz / .pkl)")
    mean = np.asarray(hands_mean, dtype=np.float64).reshape(2, 45)
    return replace(motion, left_hand_pose=np.asarray(motion.left_hand_pose) + mean[0],
                   right_hand_pose=np.asarray(motion.right_hand_pose) + mean[1])


def root_translation(motion: BodyMotion) -> np.ndarray:
    """[frames, 3] the root position the fits carry (anny: root delta translation; SMPL: transl)."""
    if motion.body_model == "anny":
        return np.asarray(motion.pose_parameters[:, 0, :3, 3], dtype=np.float64)
    return np.asarray(motion.transl, dtype=np.float64)


def check_fits(fits: BodyFits, frames: list[int], where: str) -> None:
    """Fits cover every ingested frame, and translations are metres (not millimetres)."""
    have = {int(f) for f in fits.frame_index}
    missing = [f for f in frames if f not in have]
    if missing:
        raise InputError(f"frame-count mismatch: {len(have)} body fits but {len(frames)} frames are ingested "
                         f"(no fit for frames {fmt_list(missing)})", where=where,
                         fix="add the missing fits, or select frames that have fits with --frames")
    t = fits.Th if isinstance(fits, RhThFits) else root_translation(fits)
    far = float(np.abs(t).max()) if t.size else 0.0
    if far > MAX_METRES:
        raise InputError(f"body translations reach {far:.0f}: they look like millimetres, metres are expected",
                         where=where, fix="divide the translations by 1000")


def check_cameras_metric(cameras, where: str) -> None:
    """Camera centres further than MAX_METRES from the origin mean T was written in millimetres."""
    for c in cameras:
        d = float(np.linalg.norm(c.center))
        if d > MAX_METRES:
            raise InputError(f"camera {c.name} is {d:.0f} units from the origin: T looks like millimetres, metres "
                             "are expected", where=where, fix="divide the camera translations T by 1000")
