"""The rigs motion retargeting knows: their joint names in one vocabulary and their rest poses.

Vocabulary: the SMPL-X joint names (`avatarctl.body.smpl.SMPLX_JOINT_NAMES`) plus SMPL's `left_hand` /
`right_hand` (the palm joint at the middle finger's base, `ALIASES`). A rig names each of its joints with a
vocabulary name, or leaves it unmapped (`None`; anny's own bones that no other rig has are named `anny:<bone>`, so
an anny skeleton written to BVH and read back maps bone for bone).

Rest poses:
- **SMPL / SMPL+H / SMPL-X**: the rest (T-pose) joints of the user's model file for the motion's betas when one is
  passed (`J_regressor · (v_template + shapedirs · betas)`, shape-aware); otherwise `GENERIC_T_POSE`, a generic
  adult T-pose written for avatarctl from round anthropometric numbers (y up, the subject faces +z, +x is the
  subject's left, metres; legs straight down, arms straight out, feet pointing forward). It is NOT taken from the
  licensed model: only bone *directions* matter for rotations, and SMPL's T-pose has exactly these directions to
  within a few degrees. The pelvis sits at the origin, so without a model file `transl` is read as the pelvis
  position (SMPL puts it at J_0 + transl; J_0 is a constant offset the floor alignment and `render --recenter`
  remove).
- **anny**: the bone heads of anny's reference (A-)pose for the subject's phenotype (z up, faces -y).
- **BVH**: the file's OFFSETs, joint names mapped by `BVH_NAME_MAP` (Mixamo / common names) or a user map.
"""

from __future__ import annotations

import numpy as np

from avatarctl.body.skeleton import Skeleton
from avatarctl.body.smpl import SMPL_JOINT_NAMES, SMPLX_JOINT_NAMES

# ---- the vocabulary -------------------------------------------------------------------------------------------
_SIDES = ("left", "right")
_FINGER_NAMES = ("index", "middle", "pinky", "ring", "thumb")  # SMPL-X order
BODY_22 = SMPL_JOINT_NAMES[:22]
SMPL_NAMES = SMPL_JOINT_NAMES  # 24: + left_hand, right_hand
SMPLX_NAMES = SMPLX_JOINT_NAMES  # 55: + jaw, eyes, 15 finger joints per hand
FINGERS = {"left": SMPLX_NAMES[25:40], "right": SMPLX_NAMES[40:55]}
SMPLH_NAMES = BODY_22 + FINGERS["left"] + FINGERS["right"]  # 52
RIG_NAMES = {"smpl": SMPL_NAMES, "smplh": SMPLH_NAMES, "smplx": SMPLX_NAMES}

# parent of every vocabulary joint (SMPL / SMPL-X kinematic trees)
PARENT: dict[str, str | None] = {
    "pelvis": None, "spine1": "pelvis", "spine2": "spine1", "spine3": "spine2", "neck": "spine3", "head": "neck",
    "jaw": "head", "left_eye_smplhf": "head", "right_eye_smplhf": "head",
}
for _s in _SIDES:
    PARENT.update({f"{_s}_hip": "pelvis", f"{_s}_knee": f"{_s}_hip", f"{_s}_ankle": f"{_s}_knee",
                   f"{_s}_foot": f"{_s}_ankle", f"{_s}_collar": "spine3", f"{_s}_shoulder": f"{_s}_collar",
                   f"{_s}_elbow": f"{_s}_shoulder", f"{_s}_wrist": f"{_s}_elbow", f"{_s}_hand": f"{_s}_wrist"})
    for _f in _FINGER_NAMES:
        PARENT.update({f"{_s}_{_f}1": f"{_s}_wrist", f"{_s}_{_f}2": f"{_s}_{_f}1", f"{_s}_{_f}3": f"{_s}_{_f}2"})

# SMPL's palm joint plays the middle finger's base joint of a rig with fingers (and back)
ALIASES = {"left_hand": "left_middle1", "right_hand": "right_middle1"}

# the bone each joint's rotation aims (first candidate both rigs have); lateral pairs fix the twist of branch joints
PRIMARY: dict[str, tuple[str, ...]] = {
    "pelvis": ("spine1", "spine2", "spine3", "neck"), "spine1": ("spine2", "spine3", "neck"),
    "spine2": ("spine3", "neck"), "spine3": ("neck", "head"), "neck": ("head",),
}
LATERAL: dict[str, tuple[str, str]] = {"pelvis": ("left_hip", "right_hip"), "spine1": ("left_hip", "right_hip"),
                                       "spine2": ("left_collar", "right_collar"),
                                       "spine3": ("left_collar", "right_collar"),
                                       "head": ("left_eye_smplhf", "right_eye_smplhf")}
for _s in _SIDES:
    PRIMARY.update({f"{_s}_hip": (f"{_s}_knee", f"{_s}_ankle"), f"{_s}_knee": (f"{_s}_ankle", f"{_s}_foot"),
                    f"{_s}_ankle": (f"{_s}_foot",), f"{_s}_collar": (f"{_s}_shoulder", f"{_s}_elbow"),
                    f"{_s}_shoulder": (f"{_s}_elbow", f"{_s}_wrist"), f"{_s}_elbow": (f"{_s}_wrist",),
                    f"{_s}_wrist": (f"{_s}_hand", f"{_s}_middle1")})
    for _f in _FINGER_NAMES:
        PRIMARY.update({f"{_s}_{_f}1": (f"{_s}_{_f}2", f"{_s}_{_f}3"), f"{_s}_{_f}2": (f"{_s}_{_f}3",)})

FEET = ("left_ankle", "right_ankle", "left_foot", "right_foot")  # joints whose lowest one stands on the floor
LEGS = (("left_hip", "left_knee", "left_ankle"), ("right_hip", "right_knee", "right_ankle"))
HIPS = ("left_hip", "right_hip")  # their midpoint is the point whose trajectory a retarget carries over

# joint groups for reports and figures
GROUPS = {"legs": ("hip", "knee", "ankle", "foot"), "spine": ("pelvis", "spine"), "head": ("neck", "head", "jaw",
          "eye"), "arms": ("collar", "shoulder", "elbow", "wrist"), "hands": ("hand",) + _FINGER_NAMES}


def group_of(name: str) -> str:
    """'left_knee' -> 'legs' (the vocabulary's joint groups)."""
    for g, keys in GROUPS.items():
        if any(k in name for k in keys):
            return g
    return "other"


def rig_parents(names: tuple[str, ...]) -> tuple[int, ...]:
    """Parent indices of a vocabulary rig (nearest present ancestor)."""
    idx = {n: i for i, n in enumerate(names)}
    out = []
    for n in names:
        p = PARENT[n]
        while p is not None and p not in idx:
            p = PARENT[p]
        out.append(-1 if p is None else idx[p])
    return tuple(out)


# ---- SMPL family ---------------------------------------------------------------------------------------------
_G = {  # generic adult T-pose (see module docstring): metres, y up, facing +z, +x = the subject's left
    "pelvis": (0.0, 0.0, 0.0), "spine1": (0.0, 0.10, -0.01), "spine2": (0.0, 0.23, 0.0), "spine3": (0.0, 0.29, 0.01),
    "neck": (0.0, 0.50, -0.01), "head": (0.0, 0.60, 0.03), "jaw": (0.0, 0.56, 0.06),
    "left_eye_smplhf": (0.03, 0.65, 0.09), "right_eye_smplhf": (-0.03, 0.65, 0.09),
}
for _s, _x in (("left", 1.0), ("right", -1.0)):
    _G.update({f"{_s}_hip": (0.07 * _x, -0.08, 0.0), f"{_s}_knee": (0.10 * _x, -0.47, 0.0),
               f"{_s}_ankle": (0.10 * _x, -0.87, -0.03), f"{_s}_foot": (0.11 * _x, -0.92, 0.10),
               f"{_s}_collar": (0.07 * _x, 0.41, -0.01), f"{_s}_shoulder": (0.17 * _x, 0.42, -0.01),
               f"{_s}_elbow": (0.43 * _x, 0.42, -0.01), f"{_s}_wrist": (0.68 * _x, 0.42, -0.01),
               f"{_s}_hand": (0.77 * _x, 0.42, -0.01)})
    for _f, (dy, dz, step) in {"index": (0.0, 0.025, 0.03), "middle": (0.0, 0.0, 0.033), "ring": (0.0, -0.022, 0.03),
                               "pinky": (-0.005, -0.04, 0.022)}.items():
        for _i in range(3):
            _G[f"{_s}_{_f}{_i + 1}"] = ((0.77 + _i * step) * _x, 0.42 + dy, -0.01 + dz)
    for _i, (dx, dy, dz) in enumerate(((0.03, -0.01, 0.025), (0.06, -0.015, 0.045), (0.085, -0.02, 0.06))):
        _G[f"{_s}_thumb{_i + 1}"] = ((0.68 + dx) * _x, 0.42 + dy, -0.01 + dz)
GENERIC_T_POSE: dict[str, tuple[float, float, float]] = _G


def smpl_skeleton(kind: str, rest_joints: np.ndarray | None = None) -> Skeleton:
    """The SMPL ("smpl", 24 joints), SMPL+H ("smplh", 52) or SMPL-X ("smplx", 55) skeleton.

    `rest_joints`: [J, 3] the model file's shaped rest joints (metres, y up); for "smplh" a 24-joint SMPL file's
    22 body joints are used and the fingers hang off its wrists as in `GENERIC_T_POSE`. None: `GENERIC_T_POSE`."""
    names = RIG_NAMES[kind]
    rest = np.array([GENERIC_T_POSE[n] for n in names], dtype=np.float64)
    note = "generic T-pose table (no model file)"
    if rest_joints is not None:
        rj = np.asarray(rest_joints, dtype=np.float64)
        if rj.shape == rest.shape:
            rest = rj.copy()
        elif kind == "smplh" and rj.shape == (24, 3):
            rest[:22] = rj[:22]
            for s, w in (("left", 20), ("right", 21)):
                for f in FINGERS[s]:
                    rest[names.index(f)] = rj[w] + np.array(GENERIC_T_POSE[f]) - np.array(GENERIC_T_POSE[f"{s}_wrist"])
        else:
            raise ValueError(f"rest joints {rj.shape} do not fit the {kind} skeleton ({len(names)} joints)")
        note = "model file rest joints (shape-aware)"
    return Skeleton(name=kind, joint_names=names, parents=rig_parents(names), rest=rest, canonical=names,
                    canonical_up="y", source_note=note)


# ---- anny ------------------------------------------------------------------------------------------------------
ANNY_MAP: dict[str, str] = {  # vocabulary name -> anny bone (default rig)
    "pelvis": "root", "spine1": "spine03", "spine2": "spine02", "spine3": "spine01", "neck": "neck01",
    "head": "head", "left_eye_smplhf": "eye.L", "right_eye_smplhf": "eye.R",
}
ANNY_DRIVES: dict[str, tuple[str, ...]] = {}  # vocabulary name -> anny bones that copy its rotation when unmatched
for _s, _c in (("left", "L"), ("right", "R")):
    ANNY_MAP.update({f"{_s}_hip": f"upperleg01.{_c}", f"{_s}_knee": f"lowerleg01.{_c}", f"{_s}_ankle": f"foot.{_c}",
                     f"{_s}_foot": f"toe3-1.{_c}", f"{_s}_collar": f"clavicle.{_c}",
                     f"{_s}_shoulder": f"upperarm01.{_c}", f"{_s}_elbow": f"lowerarm01.{_c}",
                     f"{_s}_wrist": f"wrist.{_c}"})
    for _n, _f in enumerate(("thumb", "index", "middle", "ring", "pinky")):
        for _i in (1, 2, 3):
            ANNY_MAP[f"{_s}_{_f}{_i}"] = f"finger{_n + 1}-{_i}.{_c}"
    ANNY_DRIVES[f"{_s}_foot"] = tuple(f"toe{t}-1.{_c}" for t in (1, 2, 4, 5))
    ANNY_DRIVES[f"{_s}_middle1"] = tuple(f"finger{t}-1.{_c}" for t in (2, 4, 5))  # an SMPL palm bends four fingers


def anny_skeleton(bone_labels: tuple[str, ...], parents: tuple[int, ...], reference_heads: np.ndarray) -> Skeleton:
    """The anny skeleton from its bone labels, parents and reference-pose bone heads [104, 3] (metres, z up;
    `AnnyBody.reference_heads`)."""
    inverse = {b: c for c, b in ANNY_MAP.items()}
    canonical = tuple(inverse.get(b, f"anny:{b}") for b in bone_labels)
    drives = {c: tuple(b for b in bones if b in bone_labels) for c, bones in ANNY_DRIVES.items()}
    return Skeleton(name="anny", joint_names=tuple(bone_labels), parents=tuple(parents), rest=reference_heads,
                    canonical=canonical, canonical_up="z", drives=drives,
                    source_note="anny reference pose for the subject's phenotype")


# ---- BVH -------------------------------------------------------------------------------------------------------
BVH_NAME_MAP: dict[str, str] = {"Hips": "pelvis", "Spine": "spine1", "Spine1": "spine2", "Spine2": "spine3",
                                "Neck": "neck", "Head": "head"}
for _s, _B in (("left", "Left"), ("right", "Right")):
    BVH_NAME_MAP.update({f"{_B}UpLeg": f"{_s}_hip", f"{_B}Leg": f"{_s}_knee", f"{_B}Foot": f"{_s}_ankle",
                         f"{_B}ToeBase": f"{_s}_foot", f"{_B}Shoulder": f"{_s}_collar", f"{_B}Arm": f"{_s}_shoulder",
                         f"{_B}ForeArm": f"{_s}_elbow", f"{_B}Hand": f"{_s}_wrist"})
    for _f, _m in (("thumb", "Thumb"), ("index", "Index"), ("middle", "Middle"), ("ring", "Ring"),
                   ("pinky", "Pinky")):
        for _i in (1, 2, 3):
            BVH_NAME_MAP[f"{_B}Hand{_m}{_i}"] = f"{_s}_{_f}{_i}"


def bvh_canonical(names: tuple[str, ...], name_map: dict[str, str] | None = None) -> tuple[str | None, ...]:
    """Vocabulary name of each BVH joint: `name_map` (user's, exact names) first, then vocabulary names used as
    they are, anny bone labels (`ANNY_MAP` / `anny:<bone>`), then `BVH_NAME_MAP` (a `mixamorig:` prefix is
    ignored). Unknown names -> None."""
    vocab = set(vocabulary())
    anny_inverse = {b: c for c, b in ANNY_MAP.items()}
    out: list[str | None] = []
    for n in names:
        if name_map and n in name_map:
            out.append(name_map[n] or None)
            continue
        bare = n.split(":", 1)[1] if n.lower().startswith("mixamorig") and ":" in n else n
        if bare in vocab:
            out.append(bare)
        elif bare in anny_inverse:
            out.append(anny_inverse[bare])
        elif bare in BVH_NAME_MAP:
            out.append(BVH_NAME_MAP[bare])
        elif _looks_like_anny(bare):
            out.append(f"anny:{bare}")
        else:
            out.append(None)
    return tuple(out)


def _looks_like_anny(name: str) -> bool:
    import re

    return re.fullmatch(r"(root|spine0\d|neck0\d|head|eye\.[LR]|[a-z]+\d*(-\d)?\.[LR])", name) is not None


def vocabulary() -> tuple[str, ...]:
    """Every vocabulary name (for error messages and docs)."""
    return tuple(dict.fromkeys(SMPLX_JOINT_NAMES + SMPL_NAMES))
