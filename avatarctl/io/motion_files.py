"""Motion files for `avatarctl render --poses`: read a pose sequence from disk into a `BodyMotion`.

Recognised layouts (`.npz`, never pickles):

- **anny** (what `avatarctl synth` writes as `motion.npz`, and any `BodyMotion.save` file such as a project's
  `ingest/body.npz`): `body_model`, `pose_parameters` [frames, 104, 4, 4] (anny "local-ref" deltas), `phenotype`
  (+ `phenotype_labels`), `frame_index`, `fps`; optional `bone_labels` (checked against the avatar's joints).
- **AMASS, SMPL+H "G" files**: `poses` [frames, 156] (root 0:3, body 3:66, hands 66:156), `trans` [frames, 3],
  `betas` [16], `mocap_framerate`. Plain SMPL sequences with `poses` [frames, 72] are read the same way.
  -> an SMPL motion: `global_orient` = poses[:, 0:3], `body_pose` = poses[:, 3:66] + zeros for SMPL's two hand joints
  (SMPL+H replaces them by finger joints, which SMPL does not have), `transl` = trans.
- **AMASS, SMPL-X "N" files**: `poses` [frames, 165] and/or `root_orient`, `pose_body`, `pose_hand`, `pose_jaw`,
  `pose_eye`; `trans`, `betas`, `mocap_frame_rate` (note the spelling). -> an SMPL-X motion (full axis-angle hands,
  no PCA; expression absent = zero).

Axis-angle in radians; translations in metres, in the motion file's own world frame (AMASS: z up).
The subject's shape (anny phenotype / SMPL betas) of a motion file is NOT the avatar's: `adopt_subject` replaces it
with the avatar's own, so only the articulation drives the avatar.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from avatarctl.body.motion import BODY_MODELS, BodyMotion
from avatarctl.errors import InputError

# body-model family a motion file drives; SMPL+H (AMASS "G") drives an SMPL avatar (same body skeleton).
MOTION_KINDS = ("anny", "smpl", "smplh", "smplx")
_FAMILY = {"anny": "anny", "smpl": "smpl", "smplh": "smpl", "smplx": "smplx"}
_MOTION_FOR = {"anny": "(an anny motion.npz as written by `avatarctl synth`)", "smpl": "(an AMASS npz for SMPL/SMPL+H)",
               "smplx": "(an AMASS npz for SMPL-X)", "toy": "(a BodyMotion npz of the toy body, e.g. ingest/body.npz)"}


def detect_motion_kind(keys: set[str], arrays: dict[str, np.ndarray], where: str) -> str:
    """Which layout an npz holds: "anny" | "smpl" | "smplh" | "smplx" (see the module docstring)."""
    if "body_model" in keys:  # a BodyMotion file (synth motion.npz, ingest/body.npz)
        bm = str(arrays["body_model"])
        if bm not in BODY_MODELS:
            raise InputError(f"motion file names an unknown body model {bm!r}", where=where,
                             fix=f"body_model must be one of {', '.join(BODY_MODELS)}")
        return bm
    if "pose_parameters" in keys:
        return "anny"
    if {"root_orient", "pose_body"} <= keys or "mocap_frame_rate" in keys or "pose_jaw" in keys:
        return "smplx"
    if "poses" in keys:
        width = arrays["poses"].shape[-1] if arrays["poses"].ndim == 2 else -1
        if width == 165:
            return "smplx"
        if width == 156:
            return "smplh"
        if width == 72:
            return "smpl"
        raise InputError(f"AMASS `poses` has shape {arrays['poses'].shape}; expected [frames, 72 | 156 | 165]",
                         where=where, fix="pass an AMASS SMPL+H (156) / SMPL-X (165) npz or an anny motion.npz")
    raise InputError(f"unrecognised motion file (keys: {', '.join(sorted(keys)) or 'none'})", where=where,
                     fix="pass an anny motion.npz (pose_parameters) or an AMASS npz (poses, trans, betas, "
                         "mocap_framerate)")


def read_motion_file(path: str | Path, body_model: str) -> BodyMotion:
    """Read `path` for an avatar built on `body_model` ("anny" | "smpl" | "smplx").

    Raises `InputError` (one line) when the file is missing, unreadable, malformed, or made for another body model.
    Frame numbers are the file's `frame_index` when present, else 0..frames-1; fps from the file (default 30).
    """
    p = Path(path)
    where = str(p)
    if not p.is_file():
        raise InputError("motion file not found", where=where, fix="check the --poses path")
    import zipfile

    if not zipfile.is_zipfile(p):
        raise InputError("cannot read motion file as .npz (not a zip archive)", where=where,
                         fix="pass a .npz written by `avatarctl synth` or an AMASS .npz")
    try:
        with np.load(p, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except ValueError as e:  # object arrays need pickles, which we never load
        raise InputError(f"motion file needs pickle to load ({e})", where=where,
                         fix="re-save it with plain numeric/string arrays (np.savez without object arrays)") from None
    except Exception as e:  # noqa: BLE001 - any unreadable file is a user input problem
        raise InputError(f"cannot read motion file as .npz ({type(e).__name__}: {e})", where=where,
                         fix="pass a .npz written by `avatarctl synth` or an AMASS .npz") from None
    kind = detect_motion_kind(set(arrays), arrays, where)
    family = _FAMILY[kind]
    if family != body_model:
        raise InputError(f"motion file is for the {_describe(kind)} body model but the avatar uses {body_model}",
                         where=where, fix=f"pass a {body_model} motion " + _MOTION_FOR[body_model])
    try:
        if "body_model" in arrays or kind == "anny":
            motion = _read_body_motion(arrays)
        elif kind in ("smpl", "smplh"):
            motion = _read_amass_smpl(arrays)
        else:
            motion = _read_amass_smplx(arrays)
    except (KeyError, ValueError) as e:
        msg = str(e).strip("'\"")
        raise InputError(f"malformed {_describe(kind)} motion file: {msg}", where=where,
                         fix="check the arrays' names and shapes against docs/render_eval.md") from None
    if motion.num_frames == 0:
        raise InputError("motion file has no frames", where=where, fix="pass a motion with at least one frame")
    return motion


def _describe(kind: str) -> str:
    return {"anny": "anny", "smpl": "SMPL", "smplh": "SMPL+H (SMPL)", "smplx": "SMPL-X"}[kind]


def _fps(arrays: dict[str, np.ndarray]) -> float:
    for key in ("fps", "mocap_framerate", "mocap_frame_rate"):
        if key in arrays:
            fps = float(np.asarray(arrays[key]).reshape(-1)[0])
            if not np.isfinite(fps) or fps <= 0:
                raise ValueError(f"{key} = {fps} is not a positive frame rate")
            return fps
    return 30.0


def _frame_index(arrays: dict[str, np.ndarray], n: int) -> np.ndarray:
    if "frame_index" in arrays:
        return np.asarray(arrays["frame_index"], dtype=np.int64).ravel()
    return np.arange(n, dtype=np.int64)


def _per_frame(arrays: dict[str, np.ndarray], key: str, dim: int) -> np.ndarray:
    a = np.asarray(arrays[key], dtype=np.float32)
    if a.ndim != 2 or a.shape[1] != dim:
        raise ValueError(f"{key} has shape {a.shape}, expected [frames, {dim}]")
    return a


def _read_body_motion(arrays: dict[str, np.ndarray]) -> BodyMotion:
    """A `BodyMotion.save` file (synth's motion.npz, a project's ingest/body.npz)."""
    from dataclasses import fields

    kw = dict(arrays)
    kw["body_model"] = str(kw.get("body_model", "anny"))
    kw["fps"] = _fps(arrays)
    first = next((kw[k] for k in ("pose_parameters", "global_orient") if k in kw), None)
    if first is None:
        raise ValueError("needs pose_parameters (anny) or global_orient/body_pose/transl (SMPL)")
    kw["frame_index"] = _frame_index(arrays, np.asarray(first).shape[0])
    if "phenotype_labels" in kw:
        kw["phenotype_labels"] = tuple(str(s) for s in kw["phenotype_labels"])
    names = {f.name for f in fields(BodyMotion)}
    return BodyMotion(**{k: v for k, v in kw.items() if k in names})


def _read_amass_smpl(arrays: dict[str, np.ndarray]) -> BodyMotion:
    poses = np.asarray(arrays["poses"], dtype=np.float32)
    n = poses.shape[0]
    body = poses[:, 3:66] if poses.shape[1] in (156, 165) else poses[:, 3:72]
    if body.shape[1] == 63:  # SMPL+H: SMPL's hand joints (22, 23) have no counterpart -> identity
        body = np.concatenate([body, np.zeros((n, 6), np.float32)], axis=1)
    trans = _per_frame(arrays, "trans", 3) if "trans" in arrays else np.zeros((n, 3), np.float32)
    betas = np.asarray(arrays["betas"], dtype=np.float32).ravel() if "betas" in arrays else None
    return BodyMotion(body_model="smpl", frame_index=_frame_index(arrays, n), fps=_fps(arrays),
                      global_orient=poses[:, :3], body_pose=body, transl=trans, betas=betas)


def _read_amass_smplx(arrays: dict[str, np.ndarray]) -> BodyMotion:
    if "poses" in arrays:
        poses = _per_frame(arrays, "poses", 165)
        parts = {"global_orient": poses[:, 0:3], "body_pose": poses[:, 3:66], "jaw_pose": poses[:, 66:69],
                 "leye_pose": poses[:, 69:72], "reye_pose": poses[:, 72:75], "left_hand_pose": poses[:, 75:120],
                 "right_hand_pose": poses[:, 120:165]}
    else:
        parts = {}
    if "root_orient" in arrays:  # separate arrays take precedence over the packed `poses`
        parts["global_orient"] = _per_frame(arrays, "root_orient", 3)
    if "pose_body" in arrays:
        parts["body_pose"] = _per_frame(arrays, "pose_body", 63)
    if "pose_jaw" in arrays:
        parts["jaw_pose"] = _per_frame(arrays, "pose_jaw", 3)
    if "pose_eye" in arrays:
        eye = _per_frame(arrays, "pose_eye", 6)
        parts["leye_pose"], parts["reye_pose"] = eye[:, :3], eye[:, 3:]
    if "pose_hand" in arrays:
        hand = _per_frame(arrays, "pose_hand", 90)
        parts["left_hand_pose"], parts["right_hand_pose"] = hand[:, :45], hand[:, 45:]
    if "global_orient" not in parts or "body_pose" not in parts:
        raise ValueError("needs `poses` [frames, 165] or `root_orient` + `pose_body`")
    n = parts["global_orient"].shape[0]
    trans = _per_frame(arrays, "trans", 3) if "trans" in arrays else np.zeros((n, 3), np.float32)
    betas = np.asarray(arrays["betas"], dtype=np.float32).ravel() if "betas" in arrays else None
    return BodyMotion(body_model="smplx", frame_index=_frame_index(arrays, n), fps=_fps(arrays), transl=trans,
                      betas=betas, **parts)


# ---- using a foreign motion on an avatar ------------------------------------------------------------------------

def root_translation(motion: BodyMotion) -> np.ndarray:
    """[frames, 3] the translation the motion applies to the whole body (anny: root delta; SMPL/-X: `transl`)."""
    if motion.body_model == "anny":
        return np.asarray(motion.pose_parameters[:, 0, :3, 3], dtype=np.float64)
    return np.asarray(motion.transl, dtype=np.float64)


def shift_motion(motion: BodyMotion, offset: np.ndarray) -> BodyMotion:
    """The motion translated by `offset` [3] metres in its world frame (every frame)."""
    off = np.asarray(offset, dtype=np.float32).reshape(3)
    if motion.body_model == "anny":
        pp = motion.pose_parameters.copy()
        pp[:, 0, :3, 3] += off
        return replace(motion, pose_parameters=pp)
    return replace(motion, transl=motion.transl + off)


def adopt_subject(motion: BodyMotion, subject: BodyMotion) -> BodyMotion:
    """`motion`'s articulation with `subject`'s body shape (anny phenotype / SMPL betas): the avatar's own body."""
    if motion.body_model != subject.body_model:
        raise InputError(f"motion is {motion.body_model} but the avatar is {subject.body_model}",
                         fix=f"pass a {subject.body_model} motion")
    if motion.body_model == "anny":
        return replace(motion, phenotype=subject.phenotype, phenotype_labels=subject.phenotype_labels)
    return replace(motion, betas=subject.betas, expression=None)


def check_joint_labels(path: str | Path, joint_names: tuple[str, ...]) -> None:
    """For anny files that carry `bone_labels`: they must be the avatar's joints, in order."""
    with np.load(path, allow_pickle=False) as z:
        if "bone_labels" not in z.files:
            return
        labels = tuple(str(s) for s in z["bone_labels"])
    if labels != tuple(joint_names):
        raise InputError(f"motion file's bone_labels ({len(labels)} bones) differ from the avatar's "
                         f"{len(joint_names)} joints", where=str(path),
                         fix="pass a motion written for the same anny rig (anny default rig, 104 bones)")
