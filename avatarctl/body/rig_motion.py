"""`BodyMotion` (per body model) <-> `SkeletonMotion` (one convention for retargeting), and the skeleton of each
body model.

- anny: local rotations = the "local-ref" deltas' rotations; the root delta's translation t places the root head:
  root_position = R_root · head_root + t (anny's root head is at the origin, so t = root_position).
- SMPL / SMPL-X: local = Rodrigues(global_orient, body_pose, jaw, eyes, hands) in joint order; the pelvis stands at
  J_0 + transl (smplx-package convention), J_0 the rest pelvis of the skeleton (0 for the generic table).
  An SMPL motion with `left_hand_pose` / `right_hand_pose` (an AMASS SMPL+H file) becomes the 52-joint SMPL+H
  skeleton with its fingers.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from avatarctl.body import rigs
from avatarctl.body.motion import BodyMotion
from avatarctl.body.skeleton import Skeleton, SkeletonMotion, axis_angle_to_matrix, matrix_to_axis_angle

TARGETS = ("anny", "smpl", "smplx")


def skeleton_of(body_model: str, motion: BodyMotion | None = None, model_path: str | Path | None = None,
                hands: bool = False) -> Skeleton:
    """The skeleton of `body_model` for `motion`'s subject (phenotype / betas). SMPL / SMPL-X use the rest joints
    of `model_path` when given (shape-aware), else the generic T-pose table; `hands` asks for SMPL+H."""
    if body_model == "anny":
        from avatarctl.body.anny_model import AnnyBody

        body = AnnyBody()
        return rigs.anny_skeleton(body.joint_names, body.parents, body.reference_heads(motion))
    if body_model in ("smpl", "smplx"):
        kind = "smplh" if body_model == "smpl" and hands else body_model
        rest = None
        if model_path is not None:
            from avatarctl.body.registry import load_body_model

            body = load_body_model(body_model, model_path)
            fit = motion if motion is not None and motion.body_model == body_model else BodyMotion(
                body_model=body_model, frame_index=np.zeros(1), global_orient=np.zeros((1, 3)),
                body_pose=np.zeros((1, 69 if body_model == "smpl" else 63)), transl=np.zeros((1, 3)))
            rest = body.rest_joints(fit)  # type: ignore[attr-defined]
        return rigs.smpl_skeleton(kind, rest)
    raise ValueError(f"no skeleton for body model {body_model!r}; expected one of {TARGETS}")


def to_skeleton_motion(motion: BodyMotion, skeleton: Skeleton, world_up: str = "z") -> SkeletonMotion:
    """`motion` as local rotations + root position on `skeleton` (built by `skeleton_of` for this body model)."""
    F = motion.num_frames
    if motion.body_model == "anny":
        pp = np.asarray(motion.pose_parameters, dtype=np.float64)
        local = pp[:, :, :3, :3]
        root = local[:, 0] @ skeleton.rest[0] + pp[:, 0, :3, 3]
    elif motion.body_model in ("smpl", "smplx"):
        parts = [motion.global_orient.reshape(F, 1, 3)]
        if skeleton.name == "smplh":
            parts += [motion.body_pose.reshape(F, 23, 3)[:, :21], motion.left_hand_pose.reshape(F, 15, 3),
                      motion.right_hand_pose.reshape(F, 15, 3)]
        elif skeleton.name == "smpl":
            parts.append(motion.body_pose.reshape(F, 23, 3))
        else:
            def get(name: str, n: int) -> np.ndarray:
                a = getattr(motion, name)
                return np.zeros((F, n, 3)) if a is None else np.asarray(a).reshape(F, n, 3)

            parts += [motion.body_pose.reshape(F, 21, 3), get("jaw_pose", 1), get("leye_pose", 1),
                      get("reye_pose", 1), get("left_hand_pose", 15), get("right_hand_pose", 15)]
        aa = np.concatenate([np.asarray(p, dtype=np.float64) for p in parts], axis=1)
        local = axis_angle_to_matrix(aa)
        root = np.asarray(motion.transl, dtype=np.float64) + skeleton.rest[0]
    else:
        raise ValueError(f"no skeleton motion for body model {motion.body_model!r}")
    return SkeletonMotion(skeleton=skeleton, local=local, root_position=root, fps=motion.fps, world_up=world_up,
                          frame_index=motion.frame_index)


def to_body_motion(sm: SkeletonMotion, body_model: str, subject: BodyMotion | None = None) -> BodyMotion:
    """A `SkeletonMotion` on `body_model`'s skeleton as a `BodyMotion` (the subject's phenotype / betas kept)."""
    skel = sm.skeleton
    F = sm.num_frames
    if body_model == "anny":
        pp = np.broadcast_to(np.eye(4), (F, skel.num_joints, 4, 4)).copy()
        pp[:, :, :3, :3] = sm.local
        pp[:, 0, :3, 3] = sm.root_position - sm.local[:, 0] @ skel.rest[0]
        out = BodyMotion(body_model="anny", frame_index=sm.frame_index, fps=sm.fps, pose_parameters=pp)
        if subject is not None and subject.body_model == "anny":
            out = replace(out, phenotype=subject.phenotype, phenotype_labels=subject.phenotype_labels)
        return out
    if body_model not in ("smpl", "smplx") or skel.name not in ("smpl", "smplx"):
        raise ValueError(f"cannot store a {skel.name} skeleton motion as a {body_model} BodyMotion")
    aa = matrix_to_axis_angle(sm.local).astype(np.float32)  # [F, J, 3]
    kw: dict[str, np.ndarray] = {"global_orient": aa[:, 0], "transl": (sm.root_position - skel.rest[0])}
    if body_model == "smpl":
        kw["body_pose"] = aa[:, 1:24].reshape(F, 69)
    else:
        kw.update(body_pose=aa[:, 1:22].reshape(F, 63), jaw_pose=aa[:, 22], leye_pose=aa[:, 23],
                  reye_pose=aa[:, 24], left_hand_pose=aa[:, 25:40].reshape(F, 45),
                  right_hand_pose=aa[:, 40:55].reshape(F, 45))
    betas = subject.betas if subject is not None and subject.body_model == body_model else None
    return BodyMotion(body_model=body_model, frame_index=sm.frame_index, fps=sm.fps, betas=betas, **kw)
