"""SMPL and SMPL-X body models read from the user's own model file (avatarctl never ships licensed files).

Model (Loper et al. 2015; Pavlakos et al. 2019), evaluated per frame f:

    v_shaped  = v_template + shapedirs · betas (+ exprdirs · expression_f for SMPL-X)   # [V, 3]
    J_rest_f  = J_regressor · v_shaped                                                   # [J, 3]
    R_fj      = Rodrigues(θ_fj)                                                          # [J, 3, 3]
    v_pose_f  = v_shaped + posedirs · vec(R_fj - I  for j >= 1)                          # pose blend shapes
    M_fj      = forward kinematics of R_f about J_rest_f, then + transl_f                # Eq. 1's M_j(θ)
    v_f       = Σ_j w_vj M_fj v_pose_f                                                   # Eq. 2 (LBS)

Conventions: metres; the world frame of the fits; axis-angle in radians. `transl` is the smplx-package
convention (the body rotates about its pelvis joint, then translates), not EasyMocap's Rh/Th. Canonical space
(`template`) is the shaped T-pose with expression zero; `joint_transforms` take canonical points (plus the
canonical-space blend offsets of `blend_offsets`) to the posed world, so LBS reproduces the posed mesh.

SMPL-X hand poses are full axis-angle rotations relative to the flat hand (smplx's `use_pca=False,
flat_hand_mean=True`); pass `add_hand_mean=True` for fits made with smplx's default `flat_hand_mean=False`,
whose hand poses are offsets from the file's `hands_mean`. SMPL-X shape directions follow the smplx package:
a file with >= 400 directions holds 300 betas then 100 expression directions, a smaller file 10 betas then
10 expression directions.

Reading: the official `.pkl` files pickle chumpy arrays and scipy sparse matrices. They are read with a
restricted unpickler that maps every `chumpy.*` class to a stand-in keeping the array value (chumpy's state
dict key `x`), so chumpy is not needed, and refuses any other Python object a model file never holds.
`.npz` files with the same keys are read without pickle.
"""

from __future__ import annotations

import zipfile
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from avatarctl.body.base import BodyTemplate, PosedBody
from avatarctl.body.lbs import axis_angle_to_matrix, forward_kinematics, lbs, matrix_to_axis_angle, transform_points
from avatarctl.body.motion import BodyMotion
from avatarctl.errors import InputError
from avatarctl.safe_pickle import SafeUnpickler, load_pickle

SMPL_JOINT_NAMES: tuple[str, ...] = (
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2", "left_ankle", "right_ankle",
    "spine3", "left_foot", "right_foot", "neck", "left_collar", "right_collar", "head", "left_shoulder",
    "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist", "left_hand", "right_hand",
)
_FINGERS = tuple(f"{finger}{i}" for finger in ("index", "middle", "pinky", "ring", "thumb") for i in (1, 2, 3))
SMPLX_JOINT_NAMES: tuple[str, ...] = (
    SMPL_JOINT_NAMES[:22] + ("jaw", "left_eye_smplhf", "right_eye_smplhf")
    + tuple(f"left_{f}" for f in _FINGERS) + tuple(f"right_{f}" for f in _FINGERS)
)
NUM_JOINTS = {"smpl": 24, "smplx": 55}
REQUIRED_KEYS = ("v_template", "shapedirs", "posedirs", "J_regressor", "weights", "kintree_table", "f")
_FIX_FILE = ("pass the official SMPL / SMPL-X model file (.pkl or .npz with v_template, shapedirs, posedirs, "
             "J_regressor, weights, kintree_table, f)")


# ---- reading the model file ----------------------------------------------------------------------------------
class _ChumpyStandIn:
    """Replaces any `chumpy.*` class while unpickling: keeps the array chumpy stores under `x` in its state."""

    def __new__(cls, *args: Any, **kwargs: Any) -> "_ChumpyStandIn":
        return object.__new__(cls)

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.x = kwargs.get("x", args[0] if args else None)

    def __setstate__(self, state: Any) -> None:
        self.x = state.get("x") if isinstance(state, dict) else None


class _ModelUnpickler(SafeUnpickler):
    """`SafeUnpickler` (numpy, scipy.sparse, builtins) plus chumpy: what SMPL model files contain."""

    def find_extra(self, module: str, name: str) -> Any | None:
        return _ChumpyStandIn if module == "chumpy" or module.startswith("chumpy.") else None


def _as_array(value: Any, key: str, path: Path) -> np.ndarray:
    """A model-file entry (ndarray, chumpy stand-in, scipy sparse) as a dense float64/int ndarray."""
    if isinstance(value, _ChumpyStandIn):
        value = value.x
    if hasattr(value, "toarray") and callable(value.toarray):  # scipy sparse
        value = value.toarray()
    if isinstance(value, np.ndarray) and value.dtype != object:
        return value
    raise InputError(f"model file entry {key!r} is a {type(value).__name__}, not an array", where=str(path),
                     fix=_FIX_FILE)


def _read_raw(path: Path) -> dict[str, Any]:
    """The key -> value mapping of a .pkl or .npz model file (format chosen by content, not extension)."""
    try:
        with open(path, "rb") as fh:
            is_zip = fh.read(4) == b"PK\x03\x04"
        if is_zip:
            with np.load(path, allow_pickle=False) as z:
                out: dict[str, Any] = {}
                for k in z.files:
                    try:
                        out[k] = z[k]
                    except ValueError:  # a pickled object entry (e.g. part2num dicts): never needed
                        continue
                return out
    except (OSError, EOFError, ValueError, zipfile.BadZipFile) as e:
        detail = " ".join(str(e).split())[:200]  # one line
        raise InputError(f"cannot read body model file: {type(e).__name__}: {detail}", where=str(path),
                         fix=_FIX_FILE) from None
    data = load_pickle(path, "body model file", _ModelUnpickler)
    if not isinstance(data, dict):
        raise InputError(f"body model file holds a {type(data).__name__}, not a dict of arrays", where=str(path),
                         fix=_FIX_FILE)
    return data


@dataclass(frozen=True)
class SmplModelData:
    """The arrays of one SMPL / SMPL-X model file, validated, float64 (faces int64)."""

    kind: str  # "smpl" | "smplx"
    v_template: np.ndarray  # [V, 3] metres
    shapedirs: np.ndarray  # [V, 3, B] identity shape directions (betas)
    exprdirs: np.ndarray  # [V, 3, E] expression directions (E = 0 for SMPL)
    posedirs: np.ndarray  # [V, 3, 9 * (J - 1)] pose blend shapes
    j_regressor: np.ndarray  # [J, V] dense joint regressor
    weights: np.ndarray  # [V, J] skinning weights
    parents: tuple[int, ...]  # [J] -1 for the root
    faces: np.ndarray  # [F, 3] int64
    hands_mean: np.ndarray | None  # [90] SMPL-X left then right hand mean pose (axis-angle), if the file has it


def read_smpl_file(path: str | Path, kind: str) -> SmplModelData:
    """Read and validate an official SMPL (`kind="smpl"`) or SMPL-X (`kind="smplx"`) model file."""
    path = Path(path)
    if kind not in NUM_JOINTS:
        raise InputError(f"unknown SMPL kind {kind!r}", fix="use smpl or smplx")
    if not path.is_file():
        raise InputError(f"{kind} model file not found", where=str(path), fix="check --body-model-path")
    raw = _read_raw(path)
    missing = [k for k in REQUIRED_KEYS if k not in raw]
    if missing:
        raise InputError(f"body model file lacks {', '.join(missing)}", where=str(path), fix=_FIX_FILE)
    a = {k: _as_array(raw[k], k, path) for k in REQUIRED_KEYS}

    def bad(msg: str) -> InputError:
        return InputError(f"body model file: {msg}", where=str(path), fix=_FIX_FILE)

    v_template = a["v_template"].astype(np.float64)
    if v_template.ndim != 2 or v_template.shape[1] != 3:
        raise bad(f"v_template has shape {v_template.shape}, expected [V, 3]")
    V = v_template.shape[0]
    kt = a["kintree_table"]
    if kt.ndim != 2 or kt.shape[0] != 2:
        raise bad(f"kintree_table has shape {kt.shape}, expected [2, J]")
    J = kt.shape[1]
    if J != NUM_JOINTS[kind]:
        other = {24: "smpl", 55: "smplx"}.get(J)
        fix = f"use --body-model {other}" if other else _FIX_FILE
        raise InputError(f"body model file has {J} joints but {kind} has {NUM_JOINTS[kind]}", where=str(path), fix=fix)
    # the root's parent is stored as -1 or as uint32 4294967295; parents must precede children
    parents = tuple(-1 if j == 0 else int(p) for j, p in enumerate(kt[0].astype(np.int64)))
    if any(not 0 <= parents[j] < j for j in range(1, J)):
        raise bad("kintree_table parents do not precede their children")

    def as3(arr: np.ndarray, key: str) -> np.ndarray:
        arr = arr.astype(np.float64)
        if arr.ndim == 2 and arr.shape[0] == V * 3:
            arr = arr.reshape(V, 3, -1)
        if arr.ndim == 2 and arr.shape == (V, 3):
            arr = arr[..., None]
        if arr.ndim != 3 or arr.shape[:2] != (V, 3):
            raise bad(f"{key} has shape {arr.shape}, expected [{V}, 3, K]")
        return arr

    shapedirs_all = as3(a["shapedirs"], "shapedirs")
    posedirs = as3(a["posedirs"], "posedirs")
    if posedirs.shape[2] != 9 * (J - 1):
        raise bad(f"posedirs has {posedirs.shape[2]} directions, expected 9 * (J - 1) = {9 * (J - 1)}")
    j_regressor = a["J_regressor"].astype(np.float64)
    if j_regressor.shape != (J, V):
        raise bad(f"J_regressor has shape {j_regressor.shape}, expected [{J}, {V}]")
    weights = a["weights"].astype(np.float64)
    if weights.shape != (V, J):
        raise bad(f"weights has shape {weights.shape}, expected [{V}, {J}]")
    faces = a["f"].astype(np.int64)
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.min() < 0 or faces.max() >= V:
        raise bad(f"f has shape {faces.shape} or indices outside [0, {V})")
    for key, arr in (("v_template", v_template), ("shapedirs", shapedirs_all), ("posedirs", posedirs),
                     ("J_regressor", j_regressor), ("weights", weights)):
        if not np.isfinite(arr).all():
            raise bad(f"{key} contains non-finite values")

    S = shapedirs_all.shape[2]
    if kind == "smplx":  # the smplx package's split of the shape space
        nb, ne = (300, 100) if S >= 400 else (min(S, 10), max(0, min(S - 10, 10)))
        shapedirs, exprdirs = shapedirs_all[..., :nb], shapedirs_all[..., nb:nb + ne]
    else:
        shapedirs, exprdirs = shapedirs_all, shapedirs_all[..., :0]
    hands_mean = None
    if kind == "smplx" and "hands_meanl" in raw and "hands_meanr" in raw:
        hl = _as_array(raw["hands_meanl"], "hands_meanl", path).astype(np.float64).ravel()
        hr = _as_array(raw["hands_meanr"], "hands_meanr", path).astype(np.float64).ravel()
        if hl.shape == (45,) and hr.shape == (45,):
            hands_mean = np.concatenate([hl, hr])
    return SmplModelData(kind=kind, v_template=v_template, shapedirs=np.ascontiguousarray(shapedirs),
                         exprdirs=np.ascontiguousarray(exprdirs), posedirs=posedirs, j_regressor=j_regressor,
                         weights=weights, parents=parents, faces=faces, hands_mean=hands_mean)


# ---- evaluating the model ------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SmplEvaluation:
    """Full SMPL / SMPL-X outputs for a motion, in the compute dtype (float64 by default)."""

    joint_transforms: torch.Tensor  # [frames, J, 4, 4] M_j(θ): canonical -> world, incl. transl (Eq. 1)
    joints: torch.Tensor  # [frames, J, 3] posed joint locations, world
    rest_joints: torch.Tensor  # [frames, J, 3] canonical joint locations (vary with expression only)
    local_rotations: torch.Tensor  # [frames, J, 3, 3] per-joint rotation relative to the parent
    blend_offsets: torch.Tensor | None  # [frames, V, 3] canonical-space expression + pose blend shape offsets
    vertices: torch.Tensor | None  # [frames, V, 3] posed vertices, world


class SmplBody:
    """`BodyModel` for SMPL (24 joints, 6890 vertices) and SMPL-X (55 joints, 10475 vertices).

    Computes in float64 (`compute_dtype`) and returns float32, batched over frames in chunks of `chunk`.
    """

    def __init__(self, data: SmplModelData, device: str | torch.device = "cpu", add_hand_mean: bool = False,
                 compute_dtype: torch.dtype = torch.float64, chunk: int = 64):
        if add_hand_mean and data.hands_mean is None:
            raise InputError("add_hand_mean needs hands_meanl / hands_meanr in the SMPL-X model file",
                             fix="use a model file with hand means, or leave add_hand_mean off")
        self.name = data.kind
        self.data = data
        self.device = torch.device(device)
        self.dtype = compute_dtype
        self.chunk = int(chunk)
        self.add_hand_mean = bool(add_hand_mean)
        self.parents = data.parents
        self.joint_names = SMPL_JOINT_NAMES if data.kind == "smpl" else SMPLX_JOINT_NAMES

        def t(x: np.ndarray) -> torch.Tensor:
            return torch.as_tensor(x, dtype=self.dtype, device=self.device)

        self.v_template = t(data.v_template)  # [V, 3]
        self.shapedirs = t(data.shapedirs)  # [V, 3, B]
        self.exprdirs = t(data.exprdirs)  # [V, 3, E]
        self.posedirs = t(data.posedirs.reshape(-1, data.posedirs.shape[2]))  # [V*3, 9(J-1)]
        self.j_regressor = t(data.j_regressor)  # [J, V]
        self.weights = t(data.weights)  # [V, J]
        # joint regressor applied to the blend directions: rest joints are linear in betas and expression
        self.j_template = self.j_regressor @ self.v_template  # [J, 3]
        self.j_shapedirs = torch.einsum("jv,vcb->jcb", self.j_regressor, self.shapedirs)  # [J, 3, B]
        self.j_exprdirs = torch.einsum("jv,vce->jce", self.j_regressor, self.exprdirs)  # [J, 3, E]
        self.faces = torch.as_tensor(data.faces, dtype=torch.int64, device=self.device)  # [F, 3]
        self.hands_mean = None if data.hands_mean is None else t(data.hands_mean)  # [90]

    @classmethod
    def from_file(cls, path: str | Path, kind: str = "smpl", device: str | torch.device = "cpu",
                  add_hand_mean: bool = False) -> "SmplBody":
        """Load the user's official SMPL / SMPL-X `.pkl` (chumpy not needed) or `.npz`."""
        return cls(read_smpl_file(path, kind), device=device, add_hand_mean=add_hand_mean)

    @property
    def num_vertices(self) -> int:
        return int(self.v_template.shape[0])

    @property
    def num_joints(self) -> int:
        return len(self.parents)

    @property
    def num_betas(self) -> int:
        return int(self.shapedirs.shape[2])

    @property
    def num_expression(self) -> int:
        return int(self.exprdirs.shape[2])

    # ---- parameters -----------------------------------------------------------------------------------------
    def _check_motion(self, motion: BodyMotion) -> None:
        if motion.body_model != self.name:
            raise InputError(f"motion is for body model {motion.body_model!r} but the model file is {self.name}",
                             fix=f"use --body-model {motion.body_model} (or re-run ingest with {self.name})")

    @staticmethod
    def _coefficients(values: np.ndarray | None, available: int, what: str, lead: tuple[int, ...]) -> np.ndarray:
        """[*lead, available] coefficients, zero-padded; extra non-zero coefficients are an error."""
        out = np.zeros((*lead, available), dtype=np.float64)
        if values is None:
            return out
        values = np.asarray(values, dtype=np.float64).reshape(*lead, -1)
        n = values.shape[-1]
        if n > available and np.any(values[..., available:] != 0):
            raise InputError(f"the motion has {n} non-zero {what} but the model file has only {available}",
                             fix=f"use a model file with >= {n} {what} directions")
        k = min(n, available)
        out[..., :k] = values[..., :k]
        return out

    def betas(self, motion: BodyMotion) -> torch.Tensor:
        """[B] shape coefficients of `motion`, zero-padded to the file's shape space."""
        return torch.as_tensor(self._coefficients(motion.betas, self.num_betas, "betas", ()), dtype=self.dtype,
                               device=self.device)

    def full_pose(self, motion: BodyMotion) -> torch.Tensor:
        """[frames, J, 3] axis-angle of every joint in joint order (SMPL-X: body, jaw, eyes, left, right hand)."""
        self._check_motion(motion)
        F = motion.num_frames
        parts = [motion.global_orient.reshape(F, 1, 3), motion.body_pose.reshape(F, -1, 3)]
        if self.name == "smplx":
            def get(name: str, dim: int) -> np.ndarray:
                a = getattr(motion, name)
                if a is None:
                    return np.zeros((F, dim // 3, 3), dtype=np.float64)
                if a.ndim != 2 or a.shape[1] != dim:
                    raise InputError(f"smplx motion {name} has shape {a.shape}, expected [frames, {dim}]",
                                     fix="store full axis-angle hand poses (no PCA), 45 values per hand")
                return a.reshape(F, dim // 3, 3)

            hands = np.concatenate([get("left_hand_pose", 45), get("right_hand_pose", 45)], axis=1)  # [F, 30, 3]
            if self.add_hand_mean:
                hands = hands + self.data.hands_mean.reshape(1, 30, 3)
            parts += [get("jaw_pose", 3), get("leye_pose", 3), get("reye_pose", 3), hands]
        pose = np.concatenate([np.asarray(p, dtype=np.float64) for p in parts], axis=1)
        assert pose.shape == (F, self.num_joints, 3), f"pose {pose.shape}"
        return torch.as_tensor(pose, dtype=self.dtype, device=self.device)

    def expression(self, motion: BodyMotion) -> torch.Tensor:
        """[frames, E] expression coefficients (zeros for SMPL or when the motion has none)."""
        coeffs = self._coefficients(motion.expression if self.name == "smplx" else None, self.num_expression,
                                    "expression coefficients", (motion.num_frames,))
        return torch.as_tensor(coeffs, dtype=self.dtype, device=self.device)

    def rest_joints(self, motion: BodyMotion) -> np.ndarray:
        """[J, 3] the shaped rest (T-pose) joints for `motion`'s betas, expression zero, float64 numpy."""
        return (self.j_template + self.j_shapedirs @ self.betas(motion)).detach().cpu().numpy().astype(np.float64)

    # ---- evaluation -----------------------------------------------------------------------------------------
    def shaped_template(self, motion: BodyMotion) -> torch.Tensor:
        """[V, 3] v_template + shapedirs · betas (expression zero), compute dtype."""
        return self.v_template + self.shapedirs @ self.betas(motion)

    def evaluate(self, motion: BodyMotion, with_vertices: bool = True) -> SmplEvaluation:
        """Every output of the model for every frame of `motion` (compute dtype), evaluated in chunks."""
        self._check_motion(motion)
        if motion.num_frames == 0:
            raise InputError("the motion has no frames", fix="pass a motion with at least one frame")
        betas = self.betas(motion)  # [B]
        pose = self.full_pose(motion)  # [F, J, 3]
        expr = self.expression(motion)  # [F, E]
        transl = torch.as_tensor(motion.transl, dtype=self.dtype, device=self.device)  # [F, 3]
        parts = [self.forward(axis_angle_to_matrix(pose[s:s + self.chunk]), betas, transl[s:s + self.chunk],
                              expr[s:s + self.chunk], with_vertices)
                 for s in range(0, motion.num_frames, self.chunk)]

        def cat(name: str) -> torch.Tensor | None:
            return None if getattr(parts[0], name) is None else torch.cat([getattr(p, name) for p in parts])

        return SmplEvaluation(joint_transforms=cat("joint_transforms"), joints=cat("joints"),
                              rest_joints=cat("rest_joints"), local_rotations=cat("local_rotations"),
                              blend_offsets=cat("blend_offsets"), vertices=cat("vertices"))

    def forward(self, rotations: torch.Tensor, betas: torch.Tensor, transl: torch.Tensor,
                expression: torch.Tensor | None = None, with_vertices: bool = True) -> SmplEvaluation:
        """The model on tensors, differentiable in every input (the module docstring's equations).

        rotations [frames, J, 3, 3] local joint rotations (root: global orientation), betas [B] (the file's B),
        transl [frames, 3], expression [frames, E] or None (zero) -> `SmplEvaluation` in the compute dtype."""
        v_shaped = self.v_template + self.shapedirs @ betas  # [V, 3]
        j_shaped = self.j_template + self.j_shapedirs @ betas  # [J, 3]
        rest_joints = j_shaped.expand(rotations.shape[0], -1, -1)  # [f, J, 3]
        if expression is not None:
            rest_joints = rest_joints + torch.einsum("jce,fe->fjc", self.j_exprdirs, expression)
        M = forward_kinematics(rotations, rest_joints, self.parents, root_translation=transl)  # [f, J, 4, 4]
        joints = transform_points(M, rest_joints)  # [f, J, 3]
        offsets = vertices = None
        if with_vertices:
            eye = torch.eye(3, dtype=rotations.dtype, device=rotations.device)
            pose_feature = (rotations[:, 1:] - eye).flatten(1)  # [f, 9(J-1)]
            offsets = (pose_feature @ self.posedirs.T).reshape(-1, self.num_vertices, 3)  # [f, V, 3]
            if expression is not None:
                offsets = offsets + torch.einsum("vce,fe->fvc", self.exprdirs, expression)
            vertices = lbs(v_shaped + offsets, self.weights, M)  # [f, V, 3]
        return SmplEvaluation(joint_transforms=M, joints=joints, rest_joints=rest_joints, local_rotations=rotations,
                              blend_offsets=offsets, vertices=vertices)

    # ---- BodyModel --------------------------------------------------------------------------------------------
    def template(self, motion: BodyMotion) -> BodyTemplate:
        """Canonical body: the shaped T-pose (expression zero), float32. Pose and expression blend shapes are
        per-frame canonical offsets (`blend_offsets`)."""
        self._check_motion(motion)
        return BodyTemplate(name=self.name, vertices=self.shaped_template(motion).float(), faces=self.faces,
                            skin_weights=self.weights.float(), parents=self.parents, joint_names=self.joint_names)

    def pose(self, motion: BodyMotion) -> PosedBody:
        """Posed mesh and M_j(θ) for every frame (float32). LBS of template + `blend_offsets` gives `vertices`."""
        ev = self.evaluate(motion)
        feats = matrix_to_axis_angle(ev.local_rotations)  # [F, J, 3], angles in [0, pi]
        feats[:, 0] = 0.0  # the root's global orientation carries no pose-dependent deformation
        return PosedBody(joint_transforms=ev.joint_transforms.float(), vertices=ev.vertices.float(),
                         pose_features=feats.float())

    def joints(self, motion: BodyMotion) -> torch.Tensor:
        """[frames, J, 3] posed joint locations, world, float32 (joint 0 is the pelvis)."""
        return self.evaluate(motion, with_vertices=False).joints.float()

    def blend_offsets(self, motion: BodyMotion) -> torch.Tensor:
        """[frames, V, 3] canonical-space pose (+ expression) blend shape offsets, float32."""
        return self.evaluate(motion).blend_offsets.float()

    def motion_from_joint_transforms(self, motion: BodyMotion, joint_transforms: torch.Tensor) -> BodyMotion:
        """The inverse of `pose` for the pose: [frames, J, 4, 4] joint transforms M'_j (canonical -> world, Eq. 1;
        e.g. refined by model/pose_refine.py) -> `motion` with the axis-angle pose and `transl` whose forward
        kinematics give them; betas, expression and the frame index are kept.

        Rotations: R_j = G_parent(j)^T G_j for the global rotations G_j (the 3x3 blocks of M'_j); the root's
        G_0 is `global_orient`. Translation: the root's transform is [G_0 | (I - G_0) r_0 + transl] for the rest
        pelvis r_0 (which moves with the SMPL-X expression), so transl = t_0 - (I - G_0) r_0. Every joint is
        inverted, SMPL-X jaw, eyes and fingers included (they come back as the input's where M' left them alone;
        with `add_hand_mean` the file's hand mean is taken off again).

        Exact when M' is a kinematic chain of this model (each joint rotating about its own rest joint, as
        `pose` and pose refinement about the model's joint centres produce). SMPL's parameters have no joint
        translations: a chain whose children are displaced from their parents' rest joints comes back with the
        rotations exact and the children placed by the model's skeleton.
        """
        self._check_motion(motion)
        M = torch.as_tensor(joint_transforms, dtype=self.dtype, device=self.device)
        F, J = motion.num_frames, self.num_joints
        if M.ndim != 4 or M.shape != (F, J, 4, 4):
            raise ValueError(f"joint_transforms must be [{F}, {J}, 4, 4], got {tuple(M.shape)}")
        G = M[..., :3, :3]  # [F, J, 3, 3] global rotations
        par = torch.as_tensor([max(p, 0) for p in self.parents], device=self.device)
        local = G[:, par].transpose(-1, -2) @ G  # [F, J, 3, 3] (the root's entry is replaced below)
        local[:, 0] = G[:, 0]
        aa = matrix_to_axis_angle(local).cpu().numpy().astype(np.float64)  # [F, J, 3]
        with torch.no_grad():
            r0 = self.evaluate(motion, with_vertices=False).rest_joints[:, 0]  # [F, 3] (expression moves it)
        transl = M[:, 0, :3, 3] - r0 + (G[:, 0] @ r0[..., None])[..., 0]  # [F, 3]
        kw: dict[str, np.ndarray] = {"global_orient": aa[:, 0], "transl": transl.cpu().numpy().astype(np.float64)}
        if self.name == "smpl":
            kw["body_pose"] = aa[:, 1:24].reshape(F, 69)
        else:
            hands = aa[:, 25:55]  # [F, 30, 3] left then right
            if self.add_hand_mean:
                hands = hands - self.data.hands_mean.reshape(1, 30, 3)
            kw.update(body_pose=aa[:, 1:22].reshape(F, 63), jaw_pose=aa[:, 22], leye_pose=aa[:, 23],
                      reye_pose=aa[:, 24], left_hand_pose=hands[:, :15].reshape(F, 45),
                      right_hand_pose=hands[:, 15:].reshape(F, 45))
        return replace(motion, **kw)
