"""Motion files for `avatarctl render --poses` and `avatarctl motion`: read a pose sequence from disk.

`read_motion` reads any of them (`MotionInput`); `read_motion_file` only a motion made for the avatar's own body
model (`avatarctl.io.motion_convert` retargets the others). Recognised layouts (npz files are read without pickle):

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
- **AIST++** `motions/*.pkl`: a pickled dict of numpy arrays `smpl_poses` [frames, 72], `smpl_trans` [frames, 3],
  `smpl_scaling` [1], read with a restricted unpickler (`avatarctl.safe_pickle`: numpy arrays and builtin
  containers only; anything else is refused). -> an SMPL motion, `transl` = smpl_trans / smpl_scaling, 60 fps,
  y up.
- **BVH** (`avatarctl.io.bvh`): any skeleton; joint names mapped to the retarget vocabulary by name (Mixamo /
  SMPL / anny names built in, others through a JSON name map). -> a `SkeletonMotion`, y up.

Axis-angle in radians; translations in metres, in the motion file's own world frame (AMASS: z up). A frame-rate
key that is none of `fps`, `mocap_framerate`, `mocap_frame_rate` but looks like one is an error, not a silent 30.
The subject's shape (anny phenotype / SMPL betas) of a motion file is NOT the avatar's: `adopt_subject` replaces it
with the avatar's own, so only the articulation drives the avatar.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from avatarctl.body.motion import BODY_MODELS, BodyMotion
from avatarctl.errors import InputError

if TYPE_CHECKING:
    from avatarctl.body.skeleton import SkeletonMotion

# body-model family a motion file drives; SMPL+H (AMASS "G") drives an SMPL avatar (same body skeleton).
MOTION_KINDS = ("anny", "smpl", "smplh", "smplx")
MOTION_FORMATS = MOTION_KINDS + ("aist", "bvh")
# (a BodyMotion file of the toy sphere body, the tests' body model, drives a toy avatar)
_FAMILY = {"anny": "anny", "smpl": "smpl", "smplh": "smpl", "smplx": "smplx", "aist": "smpl", "toy": "toy"}
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
    if "poses" in keys and not {"root_orient", "pose_body"} <= keys:
        width = arrays["poses"].shape[-1] if arrays["poses"].ndim == 2 else -1
        if width == 165:
            return "smplx"
        if width == 156:
            return "smplh"
        if width == 72:
            return "smpl"
        raise InputError(f"AMASS `poses` has shape {arrays['poses'].shape}; expected [frames, 72 | 156 | 165]",
                         where=where, fix="pass an AMASS SMPL+H (156) / SMPL-X (165) npz or an anny motion.npz")
    if {"root_orient", "pose_body"} <= keys or "mocap_frame_rate" in keys or "pose_jaw" in keys:
        return "smplx"
    raise InputError(f"unrecognised motion file (keys: {', '.join(sorted(keys)) or 'none'})", where=where,
                     fix="pass an anny motion.npz (pose_parameters) or an AMASS npz (poses, trans, betas, "
                         "mocap_framerate)")


@dataclass(frozen=True)
class MotionInput:
    """A motion file as read: a `BodyMotion` (npz, AIST++ pkl) or a `SkeletonMotion` (BVH), and its world."""

    path: str
    kind: str  # anny | smpl | smplh | smplx | aist | bvh (MOTION_FORMATS)
    body: BodyMotion | None  # npz / pkl
    skeleton: "SkeletonMotion | None"  # BVH
    world_up: str  # up axis of the motion's world: "z" (anny, AMASS) | "y" (AIST++, BVH)
    notes: tuple[str, ...] = ()

    @property
    def family(self) -> str:
        """The body model the motion is made for ("anny" | "smpl" | "smplx"), or "bvh"."""
        return "bvh" if self.kind == "bvh" else _FAMILY[self.kind]

    @property
    def num_frames(self) -> int:
        return self.body.num_frames if self.body is not None else self.skeleton.num_frames  # type: ignore[union-attr]

    @property
    def fps(self) -> float:
        return self.body.fps if self.body is not None else self.skeleton.fps  # type: ignore[union-attr]


def read_motion(path: str | Path, up: str | None = None, name_map: dict[str, str] | None = None) -> MotionInput:
    """Read any motion file avatarctl knows (module docstring), chosen by content: BVH text, AIST++ pickle, npz.

    `up` overrides the world's up axis ("y" | "z"); `name_map` maps BVH joint names to the retarget vocabulary.
    Raises `InputError` (one line: what, where, how to fix) on a missing, unreadable or malformed file.
    """
    p = Path(path)
    where = str(p)
    if not p.is_file():
        raise InputError("motion file not found", where=where, fix="check the motion file path")
    if up is not None and up not in ("y", "z"):
        raise InputError(f"unknown up axis {up!r}", where="--up", fix="use --up y or --up z")
    with open(p, "rb") as fh:
        head = fh.read(64)
    if head.removeprefix(b"\xef\xbb\xbf").lstrip().upper().startswith(b"HIERARCHY"):  # (a UTF-8 BOM allowed)
        from avatarctl.io.bvh import read_bvh

        bvh = read_bvh(p, up=up or "y", name_map=name_map)
        return MotionInput(path=where, kind="bvh", body=None, skeleton=bvh.motion, world_up=up or "y",
                           notes=bvh.notes)
    if head[:1] == b"\x80":
        body, notes = _read_aist(p)
        return MotionInput(path=where, kind="aist", body=body, skeleton=None, world_up=up or "y", notes=notes)
    import zipfile

    if not zipfile.is_zipfile(p):
        raise InputError("cannot read motion file: not an .npz, BVH or AIST++ .pkl", where=where,
                         fix="pass an anny / AMASS .npz, a .bvh or an AIST++ .pkl")
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
    try:
        if "body_model" in arrays or kind == "anny":
            motion = _read_body_motion(arrays)
        elif kind in ("smpl", "smplh"):
            motion = _read_amass_smpl(arrays)
        else:
            motion = _read_amass_smplx(arrays)
    except (KeyError, ValueError) as e:
        msg = str(e).strip("'\"")
        fix = "repair or drop the frames with NaN / inf values" if "non-finite" in msg else \
            "check the arrays' names and shapes against docs/motion.md"
        raise InputError(f"malformed {_describe(kind)} motion file: {msg}", where=where, fix=fix) from None
    if motion.num_frames == 0:
        raise InputError("motion file has no frames", where=where, fix="pass a motion with at least one frame")
    return MotionInput(path=where, kind=kind, body=motion, skeleton=None, world_up=up or "z")


def read_motion_file(path: str | Path, body_model: str) -> BodyMotion:
    """Read an npz motion made for `body_model` ("anny" | "smpl" | "smplx"), no retargeting.

    Raises `InputError` (one line) when the file is missing, unreadable, malformed, or made for another body model
    (`avatarctl.io.motion_convert` retargets those). Frame numbers are the file's `frame_index` when present, else
    0..frames-1; fps from the file (default 30).
    """
    inp = read_motion(path)
    if inp.family != body_model or inp.body is None:
        raise InputError(f"motion file is for the {_describe(inp.kind)} body model but the avatar uses {body_model}",
                         where=inp.path, fix=f"pass a {body_model} motion {_MOTION_FOR.get(body_model, '')}".strip())
    return inp.body


def _read_aist(p: Path) -> tuple[BodyMotion, tuple[str, ...]]:
    """An AIST++ motion pickle: dict of numpy arrays `smpl_poses` [frames, 72], `smpl_trans` [frames, 3],
    `smpl_scaling` [1]. Read with a restricted unpickler (numpy arrays and builtin containers only). The
    translation is `smpl_trans / smpl_scaling` (the AIST++ API's convention; the body is in metres); 60 fps."""
    from avatarctl.safe_pickle import load_pickle

    where = str(p)
    data = load_pickle(p, "AIST++ motion pickle")
    if not isinstance(data, dict):
        raise InputError(f"AIST++ pickle holds a {type(data).__name__}, not a dict", where=where,
                         fix="pass an AIST++ motions/*.pkl")
    missing = [k for k in ("smpl_poses", "smpl_trans") if k not in data]
    if missing:
        raise InputError(f"AIST++ pickle lacks {', '.join(missing)} (keys: {', '.join(map(str, data))})",
                         where=where, fix="pass an AIST++ motions/*.pkl with smpl_poses, smpl_trans, smpl_scaling")
    try:
        poses = _per_frame(data, "smpl_poses", 72)
        trans = _per_frame(data, "smpl_trans", 3)
        scaling = float(np.asarray(data.get("smpl_scaling", 1.0), dtype=np.float64).reshape(-1)[0])
        if not (np.isfinite(scaling) and scaling > 0):
            raise ValueError(f"smpl_scaling = {scaling} is not positive")
        fps = _fps(data) if any(k in data for k in FPS_KEYS) else 60.0
        motion = BodyMotion(body_model="smpl", frame_index=np.arange(poses.shape[0]), fps=fps,
                            global_orient=poses[:, :3], body_pose=poses[:, 3:], transl=trans / scaling)
    except ValueError as e:
        raise InputError(f"malformed AIST++ motion file: {e}", where=where,
                         fix="smpl_poses [frames, 72], smpl_trans [frames, 3], smpl_scaling > 0, finite values") \
            from None
    if motion.num_frames == 0:
        raise InputError("motion file has no frames", where=where, fix="pass a motion with at least one frame")
    return motion, (f"AIST++: translation = smpl_trans / smpl_scaling ({scaling:g})",)


def _describe(kind: str) -> str:
    return {"anny": "anny", "smpl": "SMPL", "smplh": "SMPL+H (SMPL)", "smplx": "SMPL-X", "aist": "AIST++ (SMPL)",
            "bvh": "BVH", "toy": "toy sphere"}[kind]


FPS_KEYS = ("fps", "mocap_framerate", "mocap_frame_rate")


def _fps(arrays: dict[str, np.ndarray]) -> float:
    """The file's frame rate (30 when it names none); a key that looks like a misspelt frame rate is an error."""
    for key in FPS_KEYS:
        if key in arrays:
            fps = float(np.asarray(arrays[key]).reshape(-1)[0])
            if not np.isfinite(fps) or fps <= 0:
                raise ValueError(f"{key} = {fps} is not a positive frame rate")
            return fps
    import difflib

    odd = [k for k in arrays if "fps" in k.lower() or "rate" in k.lower()
           or difflib.get_close_matches(k.lower(), FPS_KEYS, n=1, cutoff=0.75)]
    if odd:
        raise ValueError(f"frame-rate key {odd[0]!r} is not one of {', '.join(FPS_KEYS)} (rename it)")
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
    hands = {"left_hand_pose": poses[:, 66:111], "right_hand_pose": poses[:, 111:156]} \
        if poses.shape[1] == 156 else {}  # kept for retargeting onto rigs with fingers; SMPL ignores them
    return BodyMotion(body_model="smpl", frame_index=_frame_index(arrays, n), fps=_fps(arrays),
                      global_orient=poses[:, :3], body_pose=body, transl=trans, betas=betas, **hands)


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
