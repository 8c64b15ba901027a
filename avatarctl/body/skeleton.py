"""Skeletons and skeletal motion, the body-model-agnostic currency of motion retargeting.

A `Skeleton` is a joint tree in its rest pose; a `SkeletonMotion` is per-frame local joint rotations plus the root
joint's world position. Every rig avatarctl reads (SMPL / SMPL+H / SMPL-X, anny, BVH) shares one convention, so
one forward kinematics serves them all:

- the rest pose has every joint frame aligned with the rig's canonical axes (SMPL: its T-pose; anny: its reference
  A-pose with identity "local-ref" deltas; BVH: the zero-rotation pose of its OFFSETs);
- `local[f, j]` rotates joint j about its rest head, expressed in those canonical axes, relative to its parent:
  world rotation G_j = G_parent(j) · local_j, root: G_root = local_root (canonical -> motion world);
- posed head_j = head_parent + G_parent · (rest_j − rest_parent); head_root = `root_position`.

SMPL's `global_orient` / `body_pose` axis-angles, anny's delta rotations and BVH channel rotations are all `local`
in this sense (checked against anny's own forward pass in tests/test_retarget.py).

Frames: `Skeleton.canonical_up` / `canonical_forward` name the rig's rest axes ("y"/"+z" for SMPL and BVH,
"z"/"-y" for anny); `SkeletonMotion.world_up` names the motion world's up axis (AMASS: z, AIST++ / BVH: y,
anny: z). `to_common(...)` gives the rotation into avatarctl's common frame: anny's (+z up, subject faces −y,
+x is the subject's left). Positions are in the rig's units (`Skeleton.units_per_metre`: 1 for metres, 100 for
centimetres) -- retargeting never needs them, it scales by leg length.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

# +90 degrees about x: a y-up frame facing +z  ->  the common z-up frame facing -y (x kept: the subject's left)
Y_UP_TO_Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
UP_AXES = ("y", "z")


def to_common(up: str) -> np.ndarray:
    """[3, 3] rotation from a frame with up axis `up` ("y": facing +z, as SMPL / BVH; "z": facing -y, as anny)
    into the common frame (z up, facing -y)."""
    if up == "z":
        return np.eye(3)
    if up == "y":
        return Y_UP_TO_Z_UP.copy()
    raise ValueError(f"unknown up axis {up!r}; expected one of {UP_AXES}")


@dataclass(frozen=True)
class Skeleton:
    """A joint tree in its rest pose."""

    name: str  # "smpl" | "smplh" | "smplx" | "anny" | "bvh"
    joint_names: tuple[str, ...]  # [joints] the rig's own names
    parents: tuple[int, ...]  # [joints] parent index, -1 for the root (joint 0); parents precede children
    rest: np.ndarray  # [joints, 3] rest joint (bone head) positions, canonical axes, rig units
    canonical: tuple[str | None, ...]  # [joints] the joint's name in the retarget vocabulary, None = unmapped
    canonical_up: str = "y"  # up axis of the rest pose: "y" (facing +z) | "z" (facing -y)
    units_per_metre: float = 1.0  # 1 = metres, 100 = centimetres
    drives: dict[str, tuple[str, ...]] = field(default_factory=dict)  # canonical -> extra joints it also rotates
    source_note: str = ""  # where the rest pose came from (model file, generic table, BVH OFFSETs)

    def __post_init__(self) -> None:
        rest = np.asarray(self.rest, dtype=np.float64)
        object.__setattr__(self, "rest", rest)
        J = len(self.joint_names)
        assert rest.shape == (J, 3), f"rest {rest.shape} for {J} joints"
        assert len(self.parents) == J and len(self.canonical) == J, f"{len(self.parents)} parents, " \
            f"{len(self.canonical)} canonical names, {J} joints"
        if self.parents[0] != -1 or any(not 0 <= self.parents[j] < j for j in range(1, J)):
            raise ValueError(f"{self.name} skeleton: parents must precede children with the root first")
        if self.canonical_up not in UP_AXES:
            raise ValueError(f"canonical_up {self.canonical_up!r} not in {UP_AXES}")

    @property
    def num_joints(self) -> int:
        return len(self.joint_names)

    def index(self, name: str) -> int:
        return self.joint_names.index(name)

    def canonical_index(self) -> dict[str, int]:
        """canonical name -> joint index (mapped joints only)."""
        return {c: j for j, c in enumerate(self.canonical) if c is not None}

    def bone_length(self, chain: tuple[str, ...]) -> float | None:
        """Summed rest distance along canonical joints `chain`, or None if a joint is missing."""
        idx = self.canonical_index()
        if not all(c in idx for c in chain):
            return None
        pts = self.rest[[idx[c] for c in chain]]
        return float(np.linalg.norm(np.diff(pts, axis=0), axis=1).sum())


@dataclass(frozen=True)
class SkeletonMotion:
    """Local joint rotations of a skeleton over frames, and the root's world position."""

    skeleton: Skeleton
    local: np.ndarray  # [frames, joints, 3, 3] rotation of each joint relative to its parent (canonical axes)
    root_position: np.ndarray  # [frames, 3] root joint head in the motion world, skeleton units
    fps: float
    world_up: str = "z"  # up axis of the motion world ("y" | "z")
    frame_index: np.ndarray | None = None  # [frames] int64; None = 0..frames-1

    def __post_init__(self) -> None:
        local = np.asarray(self.local, dtype=np.float64)
        pos = np.asarray(self.root_position, dtype=np.float64)
        F = local.shape[0]
        J = self.skeleton.num_joints
        assert local.shape == (F, J, 3, 3), f"local {local.shape}, expected [{F}, {J}, 3, 3]"
        assert pos.shape == (F, 3), f"root_position {pos.shape}, expected [{F}, 3]"
        fi = np.arange(F, dtype=np.int64) if self.frame_index is None else \
            np.asarray(self.frame_index, dtype=np.int64).ravel()
        assert fi.shape == (F,), f"frame_index {fi.shape} for {F} frames"
        if not (np.isfinite(local).all() and np.isfinite(pos).all()):
            raise ValueError("motion contains non-finite rotations or positions")
        if not (np.isfinite(self.fps) and self.fps > 0):
            raise ValueError(f"fps = {self.fps} is not a positive frame rate")
        if self.world_up not in UP_AXES:
            raise ValueError(f"world_up {self.world_up!r} not in {UP_AXES}")
        object.__setattr__(self, "local", local)
        object.__setattr__(self, "root_position", pos)
        object.__setattr__(self, "frame_index", fi)

    @property
    def num_frames(self) -> int:
        return int(self.local.shape[0])

    def world_rotations(self) -> np.ndarray:
        """[frames, joints, 3, 3] G_j: canonical axes -> motion world."""
        return world_rotations(self.local, self.skeleton.parents)

    def joint_positions(self) -> np.ndarray:
        """[frames, joints, 3] posed joint heads in the motion world (skeleton units)."""
        return joint_positions(self.world_rotations(), self.skeleton.rest, self.skeleton.parents, self.root_position)

    def with_skeleton(self, skeleton: Skeleton) -> "SkeletonMotion":
        return replace(self, skeleton=skeleton)


def world_rotations(local: np.ndarray, parents: tuple[int, ...]) -> np.ndarray:
    """[frames, joints, 3, 3] local rotations -> world rotations G_j = G_parent · local_j."""
    G = np.empty_like(local)
    G[:, 0] = local[:, 0]
    for j in range(1, len(parents)):
        G[:, j] = G[:, parents[j]] @ local[:, j]
    return G


def joint_positions(G: np.ndarray, rest: np.ndarray, parents: tuple[int, ...], root: np.ndarray) -> np.ndarray:
    """Forward kinematics of joint heads: [frames, joints, 3, 3], [joints, 3], parents, [frames, 3] -> [frames,
    joints, 3]."""
    P = np.empty(G.shape[:2] + (3,), dtype=np.float64)
    P[:, 0] = root
    for j in range(1, len(parents)):
        p = parents[j]
        P[:, j] = P[:, p] + G[:, p] @ (rest[j] - rest[p])
    return P


def local_from_world(G: np.ndarray, parents: tuple[int, ...]) -> np.ndarray:
    """Inverse of `world_rotations`: local_j = G_parent^T · G_j."""
    L = np.empty_like(G)
    L[:, 0] = G[:, 0]
    par = np.array([max(p, 0) for p in parents])
    L[:, 1:] = np.swapaxes(G[:, par[1:]], -1, -2) @ G[:, 1:]
    return L


def axis_angle_to_matrix(aa: np.ndarray) -> np.ndarray:
    """[..., 3] axis-angle (radians) -> [..., 3, 3] (float64)."""
    import torch

    from avatarctl.body.lbs import axis_angle_to_matrix as aa2m

    return aa2m(torch.as_tensor(np.asarray(aa, dtype=np.float64))).numpy()


def matrix_to_axis_angle(R: np.ndarray) -> np.ndarray:
    """[..., 3, 3] -> [..., 3] axis-angle (radians, angle in [0, pi]) (float64)."""
    import torch

    from avatarctl.body.lbs import matrix_to_axis_angle as m2aa

    return m2aa(torch.as_tensor(np.asarray(R, dtype=np.float64))).numpy()


def rotation_angle(R: np.ndarray) -> np.ndarray:
    """[..., 3, 3] -> [...] rotation angle in radians (accurate near 0)."""
    return np.linalg.norm(matrix_to_axis_angle(R), axis=-1)
