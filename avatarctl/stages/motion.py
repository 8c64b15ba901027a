"""The motion stage (`avatarctl motion FILE --to anny|smpl|smplx -o OUT`): convert a motion file for one rig into
a motion for another body model, retargeting it (`avatarctl.io.motion_convert`, `avatarctl.body.retarget`).

Steps: read the file (anny / AMASS npz, AIST++ pkl, BVH; `io.motion_files.read_motion`), retarget it onto the
target body model's skeleton unless it was made for it, write OUT atomically (`.npz`: a `BodyMotion` file that
`render --poses` reads, with `provenance` (this config, the summary, the joint pairs, JSON) and, for anny, the
rig's `bone_labels`; `.bvh`: the retargeted skeleton motion, y up, centimetres) and report frames, fps, joints
mapped / dropped, the translation scale and the feet's floor error. No project is involved.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from avatarctl.errors import InputError

SCHEMA_VERSION = 1
TARGETS = ("anny", "smpl", "smplx")
OUT_SUFFIXES = (".npz", ".bvh")


@dataclass(frozen=True)
class MotionConfig:
    """What `avatarctl motion` converts."""

    source: str  # motion file: anny / AMASS .npz, AIST++ .pkl, .bvh
    to: str  # target body model: anny | smpl | smplx
    out: str  # output file: .npz (BodyMotion) | .bvh
    up: str | None = None  # the source world's up axis ("y" | "z"); None = the format's (AMASS/anny z, BVH/AIST++ y)
    world_up: str = "z"  # up axis of the output's world
    name_map: str | None = None  # JSON {BVH joint name: SMPL-X joint name}
    body_model_path: str | None = None  # the target's SMPL / SMPL-X model file (shape-aware rest joints)
    source_model_path: str | None = None  # the source's SMPL / SMPL-X model file (shape-aware rest joints)

    def __post_init__(self) -> None:
        if self.to not in TARGETS:
            raise InputError(f"unknown target body model {self.to!r}", where="--to",
                             fix=f"use one of {', '.join(TARGETS)}")
        if Path(self.out).suffix.lower() not in OUT_SUFFIXES:
            raise InputError(f"output {self.out!r} is neither .npz nor .bvh", where="-o",
                             fix="name the output OUT.npz (for render --poses) or OUT.bvh")
        for name, v in (("--up", self.up), ("--world-up", self.world_up)):
            if v is not None and v not in ("y", "z"):
                raise InputError(f"unknown up axis {v!r}", where=name, fix=f"use {name} y or {name} z")

    def to_json(self) -> dict[str, Any]:
        return {"schema_version": SCHEMA_VERSION, **asdict(self)}


@dataclass(frozen=True)
class MotionResult:
    out: Path
    source_kind: str  # anny | smpl | smplh | smplx | aist | bvh
    target: str
    frames: int
    fps: float
    retargeted: bool
    summary: str  # one line: what was done
    mapped: int  # joints mapped (0 when not retargeted)
    dropped: tuple[str, ...]  # source joints the target lacks
    scale: float  # root translation scale (1 when not retargeted)
    floor_error_cm: tuple[float, float] | None  # (mean, max) |target feet height - scaled source's|, centimetres
    notes: tuple[str, ...]
    seconds: float


def run(cfg: MotionConfig) -> MotionResult:
    """Convert `cfg.source` onto `cfg.to` and write `cfg.out` (see the module docstring)."""
    from avatarctl.io import motion_convert, motion_files

    t0 = time.perf_counter()
    if cfg.body_model_path is not None and cfg.to == "anny":
        raise InputError("--body-model-path is for SMPL / SMPL-X targets; anny needs no file", where="--body-model-path",
                         fix="drop --body-model-path (or use --source-model-path for an SMPL source)")
    inp = motion_files.read_motion(cfg.source, up=cfg.up, name_map=motion_convert.read_name_map(cfg.name_map))
    conv = motion_convert.convert_motion(inp, cfg.to, model_path=cfg.body_model_path,
                                         source_model_path=cfg.source_model_path, world_up=cfg.world_up)
    out = Path(cfg.out)
    floor = None
    if conv.report is not None and conv.source is not None and conv.target is not None:
        from avatarctl.body.retarget import floor_errors

        fe = floor_errors(conv.source, conv.target, conv.report)
        err = fe.height_error * 100.0 / conv.target.skeleton.units_per_metre
        floor = (float(err.mean()), float(err.max()))
    r = conv.report
    _write(out, cfg, inp, conv)
    return MotionResult(out=out, source_kind=inp.kind, target=cfg.to, frames=conv.motion.num_frames,
                        fps=float(conv.motion.fps), retargeted=r is not None, summary=conv.summary(inp.kind),
                        mapped=len(r.mapped) if r else 0, dropped=r.dropped if r else (),
                        scale=r.scale if r else 1.0, floor_error_cm=floor, notes=conv.notes,
                        seconds=time.perf_counter() - t0)


def _write(out: Path, cfg: MotionConfig, inp: Any, conv: Any) -> None:
    """OUT.bvh: the motion on the target's skeleton; OUT.npz: the `BodyMotion` plus provenance (and anny's
    `bone_labels`)."""
    if out.suffix.lower() == ".bvh":
        from avatarctl.io.bvh import write_bvh

        sm = conv.target
        if sm is None:  # the file was made for the target already: write it on the target's own skeleton
            from avatarctl.body import rig_motion

            motion = conv.motion
            hands = motion.body_model == "smpl" and motion.left_hand_pose is not None
            skel = rig_motion.skeleton_of(motion.body_model, motion, cfg.body_model_path, hands=hands)
            sm = rig_motion.to_skeleton_motion(motion, skel, world_up=inp.world_up)
        write_bvh(out, sm)
        return
    r = conv.report
    record = {**cfg.to_json(), "source_kind": inp.kind, "summary": conv.summary(inp.kind), "notes": list(conv.notes),
              "mapped": [list(p) for p in r.mapped] if r else [], "dropped": list(r.dropped) if r else [],
              "scale": r.scale if r else 1.0}
    extra = {"provenance": np.array(json.dumps(record))}
    if conv.target is not None and cfg.to == "anny":  # render --poses checks them against the avatar's rig
        extra["bone_labels"] = np.array(conv.target.skeleton.joint_names)
    conv.motion.save(out, extra=extra)
