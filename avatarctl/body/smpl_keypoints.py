"""COCO-17 (+ heels and big toes) keypoints of SMPL / SMPL-X, and the SMPL side of the keypoint fit.

Where each keypoint comes from (`smpl_keypoint_map`, decided once per model file at load time):

- **body joints** -- shoulders, elbows, wrists, hips, knees, ankles: the model's own joints (its `J_regressor`
  on the shaped rest mesh, then forward kinematics), which carry the COCO names in `SMPL_JOINT_NAMES`.
  *Convention gap at the hips*: SMPL's hip joints are rotation centres inside the pelvis, while COCO / MediaPipe
  mark the hip lower and more to the front (on anny, whose COCO regressor imitates the annotations, the COCO hip
  sits 2.2-4.2 cm from the rig's hip joint over the phenotype range: 1.7-3.2 cm lower, 0.5-2.3 cm to the front;
  `docs/experiments/smpl_keypoints_2026-11-25/`). No offset is added (the gap on a real SMPL file cannot be measured here); the hips
  get the weight `HIP_WEIGHT` in the fit instead, so the knees and shoulders place the pelvis.
- **face** -- picked from the template's vertices by geometry: the nose is the most anterior vertex of the
  head (vertices whose largest skinning weight is the `head` joint); each ear is the head's most lateral vertex
  on its side. SMPL-X eyes are its eyeball joints (`left_eye_smplhf`, `right_eye_smplhf`: the centre of the
  eyeball, about one eyeball radius behind the pupil MediaPipe marks). **SMPL has no eye point**: it has no eye
  joint, and the eye sits in a concave socket with no extremal vertex to pick; nose and ears already fix the
  head's orientation, so the SMPL eyes are dropped (`SmplKeypointMap.dropped` says so).
- **feet** -- big toe: the most anterior vertex of the side's `foot` joint (SMPL's foot joint is the ball of the
  foot, the toes hang off it); heel: the most posterior-inferior vertex (extreme along -forward - up) of the
  side's `ankle` joint.

Directions are the model's own, from its rest joints: lateral = subject's right -> left (shoulders and hips),
up = pelvis -> head made orthogonal to it, forward = lateral x up (SMPL: +x, +y, +z). So the picks are defined
for any file in the official format; on a real SMPL file they have not been checked against a photo here (no
licensed file on this machine).

`SmplKeypoints` is the `KeypointBody` of the fit (`avatarctl.body.fit_keypoints`): per-frame rotations of the 21
body joints below the pelvis (SMPL's two hand joints, SMPL-X's jaw, eyes and fingers stay at zero: no keypoint
sees them), a root pose, and the first `NUM_FIT_BETAS` betas shared by the frames.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from avatarctl.body.lbs import axis_angle_to_matrix, matrix_to_axis_angle
from avatarctl.body.motion import BodyMotion
from avatarctl.body.smpl import SMPL_JOINT_NAMES, SMPLX_JOINT_NAMES, SmplBody, SmplModelData

JOINT_KEYPOINTS = ("left_shoulder", "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist",
                   "left_hip", "right_hip", "left_knee", "right_knee", "left_ankle", "right_ankle")  # = joint names
SMPLX_EYES = {"left_eye": "left_eye_smplhf", "right_eye": "right_eye_smplhf"}
VERTEX_KEYPOINTS = ("nose", "left_ear", "right_ear", "left_heel", "right_heel", "left_big_toe", "right_big_toe")
HIP_WEIGHT = 0.5  # relative weight of the hips in the fit (the convention gap above)
FIT_JOINTS = SMPL_JOINT_NAMES[1:22]  # the body joints the fit rotates (SMPL and SMPL-X share them)
NUM_FIT_BETAS = 10  # betas fitted (the first ten; a 300-beta SMPL-X file keeps the rest at zero)
BETA_PRIOR_SCALE = 4.0  # shape prior ‖β / 4‖²: β = ±2 costs what anny's extreme phenotype (0 or 1) costs
NO_SMPL_EYES = "SMPL has no eye joint and no extremal eye vertex (nose and ears fix the head)"


@dataclass(frozen=True)
class SmplKeypointMap:
    """Which joint or vertex stands for each keypoint of one model file."""

    names: tuple[str, ...]  # [joints] the keypoints provided, in the order they were asked for
    joint: np.ndarray  # [joints] int64 model joint index, -1 where the keypoint is a vertex
    vertex: np.ndarray  # [joints] int64 template vertex index, -1 where the keypoint is a joint
    dropped: dict[str, str] = field(default_factory=dict)  # asked-for name -> why the model cannot provide it


def body_axes(rest_joints: np.ndarray, joint_names: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(lateral, up, forward) unit vectors [3] of a rest pose [J, 3] (see the module docstring)."""
    j = {n: rest_joints[i] for i, n in enumerate(joint_names)}
    lateral = j["left_shoulder"] - j["right_shoulder"] + j["left_hip"] - j["right_hip"]
    lateral = lateral / np.linalg.norm(lateral)
    up = j["head"] - j["pelvis"]
    up = up - (up @ lateral) * lateral
    up = up / np.linalg.norm(up)
    return lateral, up, np.cross(lateral, up)


def smpl_keypoint_map(data: SmplModelData, names: tuple[str, ...]) -> SmplKeypointMap:
    """The keypoint sources of `names` for the model file `data` (rest template, betas zero)."""
    joint_names = SMPL_JOINT_NAMES if data.kind == "smpl" else SMPLX_JOINT_NAMES
    rest = data.j_regressor @ data.v_template  # [J, 3]
    lateral, up, forward = body_axes(rest, joint_names)
    owner = data.weights.argmax(1)  # [V] the joint each vertex follows most

    def extreme(joint: str, direction: np.ndarray) -> int:
        idx = np.flatnonzero(owner == joint_names.index(joint))
        if idx.size == 0:
            raise ValueError(f"no vertex of the model follows its {joint} joint")
        return int(idx[np.argmax(data.v_template[idx] @ direction)])

    picks = {"nose": ("head", forward), "left_ear": ("head", lateral), "right_ear": ("head", -lateral),
             "left_heel": ("left_ankle", -forward - up), "right_heel": ("right_ankle", -forward - up),
             "left_big_toe": ("left_foot", forward), "right_big_toe": ("right_foot", forward)}
    eyes = SMPLX_EYES if data.kind == "smplx" else {}
    kept, joint, vertex, dropped = [], [], [], {}
    for n in names:
        if n in JOINT_KEYPOINTS or n in eyes:
            kept.append(n)
            joint.append(joint_names.index(eyes.get(n, n)))
            vertex.append(-1)
        elif n in picks:
            kept.append(n)
            joint.append(-1)
            vertex.append(extreme(*picks[n]))
        elif n in ("left_eye", "right_eye"):
            dropped[n] = NO_SMPL_EYES
        else:
            dropped[n] = f"no {data.kind} keypoint named {n!r}"
    return SmplKeypointMap(names=tuple(kept), joint=np.array(joint, dtype=np.int64),
                           vertex=np.array(vertex, dtype=np.int64), dropped=dropped)


def gather_keypoints(kmap: SmplKeypointMap, joints: torch.Tensor, vertices: torch.Tensor) -> torch.Tensor:
    """Posed joints [frames, J, 3] and vertices [frames, V, 3] -> keypoints [frames, joints, 3] of `kmap`."""
    is_joint = torch.as_tensor(kmap.joint >= 0)
    from_joints = joints[:, torch.as_tensor(np.maximum(kmap.joint, 0))]
    from_verts = vertices[:, torch.as_tensor(np.maximum(kmap.vertex, 0))]
    return torch.where(is_joint[None, :, None], from_joints, from_verts)


class SmplKeypoints:
    """`KeypointBody` for SMPL / SMPL-X (see the module docstring). Root pose: a point rigid with the pelvis goes
    to ``R_root x + t_root`` (the rotation is about the world origin, as anny's root delta); `to_motion` turns it
    into SMPL's `global_orient` / `transl` (rotation about the shaped rest pelvis J0: transl = t + R J0 - J0)."""

    def __init__(self, body: SmplBody, names: tuple[str, ...]):
        self.body = body
        self.body_model = body.name
        self.kmap = smpl_keypoint_map(body.data, names)
        self.names = self.kmap.names
        self.weight = np.array([HIP_WEIGHT if n.endswith("_hip") else 1.0 for n in self.names])  # [joints]
        self.num_rotations = len(FIT_JOINTS)
        self.num_shape = min(NUM_FIT_BETAS, body.num_betas)
        self.dtype = body.dtype
        self._fit_index = torch.as_tensor([body.joint_names.index(n) for n in FIT_JOINTS])

    def _betas(self, shape: torch.Tensor) -> torch.Tensor:
        """[num_shape] -> [B] the file's betas (the rest zero)."""
        return torch.cat([shape, shape.new_zeros(self.body.num_betas - self.num_shape)])

    def _transl(self, R_root: torch.Tensor, t_root: torch.Tensor, betas: torch.Tensor) -> torch.Tensor:
        j0 = self.body.j_template[0] + self.body.j_shapedirs[0] @ betas  # [3] shaped rest pelvis
        return t_root + (R_root @ j0) - j0

    def keypoints(self, rotvecs: torch.Tensor, R_root: torch.Tensor, t_root: torch.Tensor,
                  shape: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """rotvecs [frames, 21, 3], R_root [frames, 3, 3], t_root [frames, 3], shape [num_shape] (betas) ->
        (keypoints [frames, joints, 3], vertices [frames, V, 3]), world metres."""
        f = rotvecs.shape[0]
        betas = self._betas(shape)
        rot = torch.eye(3, dtype=self.dtype).repeat(f, self.body.num_joints, 1, 1)
        rot = rot.index_put((torch.arange(f)[:, None], self._fit_index[None]), axis_angle_to_matrix(rotvecs))
        rot = torch.cat([R_root[:, None], rot[:, 1:]], dim=1)
        ev = self.body.forward(rot, betas, self._transl(R_root, t_root, betas))
        return gather_keypoints(self.kmap, ev.joints, ev.vertices), ev.vertices

    def shape_prior(self, shape: torch.Tensor) -> torch.Tensor:
        return ((shape / BETA_PRIOR_SCALE) ** 2).sum()

    def limit_penalty(self, rotvecs: torch.Tensor) -> torch.Tensor:
        """No joint limits for SMPL / SMPL-X yet (their hinge axes are not checked on a real model file): zeros."""
        return rotvecs.new_zeros(rotvecs.shape[0])

    def to_motion(self, rotvecs: torch.Tensor, R_root: torch.Tensor, t_root: torch.Tensor,
                  shape: torch.Tensor) -> BodyMotion:
        """The fitted parameters as a `BodyMotion` (frame_index 0..frames-1; SMPL-X hands and face zero)."""
        f = rotvecs.shape[0]
        betas = self._betas(shape)
        body_pose = torch.zeros(f, (69 if self.body_model == "smpl" else 63) // 3, 3, dtype=self.dtype)
        body_pose[:, :len(FIT_JOINTS)] = rotvecs
        kw = {}
        if self.body_model == "smplx":
            kw = {n: np.zeros((f, d)) for n, d in (("jaw_pose", 3), ("leye_pose", 3), ("reye_pose", 3),
                                                   ("left_hand_pose", 45), ("right_hand_pose", 45),
                                                   ("expression", self.body.num_expression))}
        return BodyMotion(body_model=self.body_model, frame_index=np.arange(f),
                          global_orient=matrix_to_axis_angle(R_root).numpy(), body_pose=body_pose.reshape(f, -1).numpy(),
                          transl=self._transl(R_root, t_root, betas).numpy(), betas=shape.numpy(), **kw)
