"""A motion file for any rig -> a `BodyMotion` for a chosen body model, retargeting when the rigs differ.

`convert_motion(read_motion(path), to="anny", subject=...)`:
- the motion is for `to` already (anny npz onto anny, AMASS SMPL+H / SMPL / AIST++ onto SMPL, AMASS SMPL-X onto
  SMPL-X): returned as read, no retarget (SMPL+H fingers are dropped for SMPL, with a note);
- otherwise its skeleton (`avatarctl.body.rig_motion.skeleton_of`, the BVH's own) is retargeted onto `to`'s
  (`avatarctl.body.retarget`): SMPL / SMPL-X rest joints come from a model file when one is given (the source's
  for the source, the avatar's for the target: shape-aware), else from the generic T-pose table; anny's from its
  reference pose for the subject's phenotype.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from pathlib import Path

from avatarctl.body.motion import BodyMotion
from avatarctl.body.retarget import RetargetReport
from avatarctl.body.skeleton import SkeletonMotion
from avatarctl.errors import InputError
from avatarctl.io.motion_files import MotionInput

TARGETS = ("anny", "smpl", "smplx")


@dataclass(frozen=True)
class ConvertedMotion:
    """A motion on the target body model and how it got there."""

    motion: BodyMotion  # on the target body model
    target: SkeletonMotion | None  # on the target skeleton (None when no retarget was needed)
    source: SkeletonMotion | None  # the source on its own skeleton (None when no retarget was needed)
    report: RetargetReport | None  # None: the file was made for the target already
    notes: tuple[str, ...]

    @property
    def retargeted(self) -> bool:
        return self.report is not None

    def summary(self, source_kind: str) -> str:
        """One line for CLI summaries."""
        if self.report is None:
            return f"{source_kind} motion used as is (made for {self.motion.body_model})"
        r = self.report
        return (f"retargeted {source_kind} ({r.source} skeleton) -> {r.target}: {len(r.mapped)} joints mapped, "
                f"{len(r.dropped)} dropped, root translation x{r.scale:.3g} (leg length)")


def read_name_map(path: str | Path | None) -> dict[str, str] | None:
    """A JSON object {BVH joint name: vocabulary name (or null to ignore the joint)}."""
    if path is None:
        return None
    p = Path(path)
    try:
        data = json.loads(p.read_text())
    except (OSError, ValueError) as e:
        raise InputError(f"cannot read the joint name map ({type(e).__name__})", where=str(p),
                         fix='pass a JSON object such as {"Hips": "pelvis", "LeftUpLeg": "left_hip"}') from None
    if not isinstance(data, dict) or not all(isinstance(k, str) and (v is None or isinstance(v, str))
                                             for k, v in data.items()):
        raise InputError("the joint name map is not a JSON object of names", where=str(p),
                         fix='pass a JSON object such as {"Hips": "pelvis", "LeftUpLeg": "left_hip"}')
    from avatarctl.body.rigs import vocabulary

    unknown = sorted(v for v in data.values() if v is not None and v not in vocabulary())
    if unknown:
        raise InputError(f"the joint name map names unknown joints: {', '.join(unknown[:5])}", where=str(p),
                         fix="map onto SMPL-X joint names (pelvis, left_hip, left_knee, ..., see docs/motion.md)")
    return data


def convert_motion(inp: MotionInput, to: str, subject: BodyMotion | None = None,
                   model_path: str | Path | None = None, source_model_path: str | Path | None = None,
                   world_up: str = "z") -> ConvertedMotion:
    """`inp` as a `BodyMotion` of body model `to` (see the module docstring). `subject`: the avatar's own fits
    (phenotype / betas of the target); `world_up`: the up axis of the result's world."""
    if to not in TARGETS:
        raise InputError(f"cannot retarget motion onto the {to!r} body model", where=inp.path,
                         fix=f"motion retargeting targets {', '.join(TARGETS)}")
    if inp.family == to and inp.body is not None:
        motion, notes = inp.body, list(inp.notes)
        if inp.kind == "smplh" and motion.left_hand_pose is not None:
            motion = replace(motion, left_hand_pose=None, right_hand_pose=None)
            notes.append("SMPL+H finger joints dropped: SMPL has none")
        return ConvertedMotion(motion=motion, target=None, source=None, report=None, notes=tuple(notes))

    from avatarctl.body import rig_motion
    from avatarctl.body.retarget import retarget

    try:
        if inp.skeleton is not None:
            src = inp.skeleton
        else:
            body = inp.body
            assert body is not None
            hands = body.body_model == "smpl" and body.left_hand_pose is not None
            skel = rig_motion.skeleton_of(body.body_model, body, source_model_path, hands=hands)
            src = rig_motion.to_skeleton_motion(body, skel, world_up=inp.world_up)
        target_skel = rig_motion.skeleton_of(to, subject if subject is not None and subject.body_model == to
                                             else None, model_path)
        out, report = retarget(src, target_skel, world_up=world_up)
    except ValueError as e:
        mapped = sum(c is not None for c in (inp.skeleton.skeleton.canonical if inp.skeleton else ()))
        extra = f" ({mapped} of {inp.skeleton.skeleton.num_joints} joints have known names)" if inp.skeleton else ""
        raise InputError(f"cannot retarget this {inp.kind} motion onto {to}: {e}{extra}", where=inp.path,
                         fix="name its joints with --name-map map.json ({\"Hips\": \"pelvis\", ...}, SMPL-X joint "
                             "names) so that the pelvis, hips, knees and ankles are known") from None
    motion = rig_motion.to_body_motion(out, to, subject)
    return ConvertedMotion(motion=motion, target=out, source=src, report=report,
                           notes=tuple(inp.notes) + report.notes)
