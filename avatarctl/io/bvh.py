"""BVH (Biovision hierarchy) motion files: a small reader and writer over `SkeletonMotion`.

Written here rather than taken from PyPI: the format is small, and the round trip anny -> BVH -> anny must hold
to 1e-4 rad, which needs control over the Euler convention and the printed precision.

Conventions (those of the common BVH exporters: Blender, MotionBuilder, CMU):
- a joint's transform is Translate(OFFSET) · R, R the product of its rotation channels *in the listed order*
  (`Zrotation Xrotation Yrotation` -> R = Rz · Rx · Ry, column vectors), angles in degrees; world rotations
  compose down the tree, so BVH rotations are exactly `SkeletonMotion.local` (the zero-rotation pose is the rest);
- the root's position channels are its absolute position (its OFFSET when it has none); position channels of
  other joints are read and ignored (reported in `BvhFile.notes`); `End Site` blocks carry no joint;
- y is up and the subject faces +z unless told otherwise (`up`); lengths in the file's unit (`units_per_metre`
  guessed from the leg length: > 5 units per leg means centimetres, else metres; only reports use it,
  retargeting scales by leg length).

The writer emits `Zrotation Yrotation Xrotation` channels with six decimals (1e-8 rad), the skeleton converted
to y up in centimetres, so an anny motion written and read back gives the same rotations.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from avatarctl.body import rigs
from avatarctl.body.skeleton import Skeleton, SkeletonMotion, local_from_world, to_common
from avatarctl.errors import InputError

_AXES = {"X": 0, "Y": 1, "Z": 2}
_FIX = "pass a BVH file (HIERARCHY with ROOT/JOINT/OFFSET/CHANNELS, then MOTION, Frames:, Frame Time:)"


@dataclass(frozen=True)
class BvhFile:
    """What a BVH file held, as a skeleton motion plus what was ignored."""

    motion: SkeletonMotion
    notes: tuple[str, ...]


def _axis_rotation(axis: int, deg: np.ndarray) -> np.ndarray:
    """[frames] degrees about axis 0/1/2 -> [frames, 3, 3]."""
    a = np.radians(deg)
    c, s = np.cos(a), np.sin(a)
    R = np.zeros(a.shape + (3, 3))
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    R[..., axis, axis] = 1.0
    R[..., i, i], R[..., j, j], R[..., i, j], R[..., j, i] = c, c, -s, s
    return R


def read_bvh(path: str | Path, up: str = "y", name_map: dict[str, str] | None = None) -> BvhFile:
    """Read a BVH file. Raises `InputError` (one line, with the line number) on malformed files."""
    p = Path(path)
    where = str(p)
    try:
        text = p.read_text(encoding="utf-8", errors="replace")
    except OSError as e:
        raise InputError(f"cannot read BVH file ({e.strerror})", where=where, fix=_FIX) from None
    tokens: list[tuple[int, str]] = [(n + 1, t) for n, line in enumerate(text.splitlines()) for t in line.split()]
    pos = 0

    def fail(msg: str) -> InputError:
        line = tokens[min(pos, len(tokens) - 1)][0] if tokens else 0
        return InputError(f"malformed BVH: {msg}", where=f"{where}:{line}", fix=_FIX)

    def take(expect: str | None = None) -> str:
        nonlocal pos
        if pos >= len(tokens):
            raise fail(f"unexpected end of file{f' (expected {expect})' if expect else ''}")
        tok = tokens[pos][1]
        if expect is not None and tok.upper() != expect.upper():
            raise fail(f"expected {expect!r}, found {tok!r}")
        pos += 1
        return tok

    def number() -> float:
        tok = take()
        try:
            return float(tok)
        except ValueError:
            raise fail(f"expected a number, found {tok!r}") from None

    names: list[str] = []
    parents: list[int] = []
    offsets: list[np.ndarray] = []
    channels: list[list[str]] = []
    take("HIERARCHY")
    take("ROOT")

    def joint(parent: int) -> None:
        name = take()
        me = len(names)
        names.append(name)
        parents.append(parent)
        take("{")
        take("OFFSET")
        offsets.append(np.array([number(), number(), number()]))
        chans: list[str] = []
        if pos < len(tokens) and tokens[pos][1].upper() == "CHANNELS":
            take()
            n = int(number())
            chans = [take() for _ in range(n)]
            bad = [c for c in chans if c[:1].upper() not in _AXES or c[1:].lower() not in ("position", "rotation")]
            if bad:
                raise fail(f"unknown channel {bad[0]!r} of joint {name!r}")
        channels.append(chans)
        while True:
            tok = take().upper()
            if tok == "JOINT":
                joint(me)
            elif tok == "END":
                take("Site")
                take("{")
                take("OFFSET")
                number(), number(), number()
                take("}")
            elif tok == "}":
                return
            else:
                raise fail(f"unexpected {tokens[pos - 1][1]!r} in joint {name!r}")

    joint(-1)
    take("MOTION")
    take("Frames:")
    frames = int(number())
    take("Frame")
    take("Time:")
    frame_time = number()
    if not frame_time > 0:
        raise fail(f"Frame Time {frame_time} is not positive")
    width = sum(len(c) for c in channels)
    values = tokens[pos:]
    if len(values) != frames * width:
        raise InputError(f"malformed BVH: {len(values)} motion values, expected {frames} frames x {width} channels",
                         where=where, fix="check the Frames: count and the CHANNELS of every joint")
    try:
        data = np.array([float(v) for _, v in values], dtype=np.float64).reshape(frames, width)
    except ValueError as e:
        raise InputError(f"malformed BVH: a motion value is not a number ({e})", where=where, fix=_FIX) from None
    if frames == 0:
        raise InputError("BVH file has no frames", where=where, fix="pass a motion with at least one frame")
    if not np.isfinite(data).all():
        row = int(np.argwhere(~np.isfinite(data))[0, 0])
        raise InputError(f"BVH motion has non-finite values (frame {row})", where=where,
                         fix="remove or repair the frames with NaN / inf")

    J = len(names)
    rest = np.zeros((J, 3))
    for j in range(J):
        rest[j] = offsets[j] + (rest[parents[j]] if j else 0.0)
    local = np.broadcast_to(np.eye(3), (frames, J, 3, 3)).copy()
    root = np.broadcast_to(offsets[0], (frames, 3)).copy()
    col = 0
    moving = []
    for j, chans in enumerate(channels):
        R = np.broadcast_to(np.eye(3), (frames, 3, 3))
        for c in chans:
            axis, kind = _AXES[c[0].upper()], c[1:].lower()
            if kind == "rotation":
                R = R @ _axis_rotation(axis, data[:, col])
            elif j == 0:
                root[:, axis] = data[:, col]
            elif np.any(data[:, col] != 0):
                moving.append(names[j])
            col += 1
        local[:, j] = R
    notes = [f"position channels of {len(set(moving))} non-root joints ignored"] if moving else []
    canonical = rigs.bvh_canonical(tuple(names), name_map)
    legs = [np.linalg.norm(np.diff(rest[[names.index(n) for n in chain]], axis=0), axis=1).sum()
            for chain in _leg_chains(names, canonical)]
    units = 100.0 if legs and float(np.mean(legs)) > 5.0 else 1.0
    skel = Skeleton(name="bvh", joint_names=tuple(names), parents=tuple(parents), rest=rest, canonical=canonical,
                    canonical_up=up, units_per_metre=units, source_note=f"BVH OFFSETs of {p.name}")
    motion = SkeletonMotion(skeleton=skel, local=local, root_position=root, fps=1.0 / frame_time, world_up=up)
    return BvhFile(motion=motion, notes=tuple(notes))


def _leg_chains(names: list[str], canonical: tuple[str | None, ...]) -> list[list[str]]:
    by = {c: n for n, c in zip(names, canonical) if c is not None}
    return [[by[c] for c in chain] for chain in rigs.LEGS if all(c in by for c in chain)]


def _zyx_degrees(R: np.ndarray) -> np.ndarray:
    """[..., 3, 3] -> [..., 3] (z, y, x) degrees with R = Rz · Ry · Rx."""
    cy = np.sqrt(R[..., 2, 1] ** 2 + R[..., 2, 2] ** 2)
    regular = cy > 1e-9
    z = np.where(regular, np.arctan2(R[..., 1, 0], R[..., 0, 0]), np.arctan2(-R[..., 0, 1], R[..., 1, 1]))
    x = np.where(regular, np.arctan2(R[..., 2, 1], R[..., 2, 2]), 0.0)
    y = np.arctan2(-R[..., 2, 0], cy)
    return np.degrees(np.stack([z, y, x], axis=-1))


def bvh_text(sm: SkeletonMotion, units_per_metre: float = 100.0) -> str:
    """A skeleton motion as BVH text: y up (facing +z), `units_per_metre` (default centimetres)."""
    skel = sm.skeleton
    A = to_common("y").T  # common -> BVH's y-up frame
    C, V = to_common(skel.canonical_up), to_common(sm.world_up)
    scale = units_per_metre / skel.units_per_metre
    rest = skel.rest @ (A @ C).T * scale  # [joints, 3] in the BVH frame
    G = A @ V @ sm.world_rotations() @ C.T @ A.T  # BVH canonical -> BVH world
    local = local_from_world(G, skel.parents)
    root = sm.root_position @ (A @ V).T * scale
    children: dict[int, list[int]] = {}
    for j, p in enumerate(skel.parents):
        children.setdefault(p, []).append(j)
    lines = ["HIERARCHY"]
    order: list[int] = []  # joints in file order (depth first), which is the order of the motion values

    def emit(j: int, depth: int) -> None:
        order.append(j)
        ind = "  " * depth
        off = rest[j] - (rest[skel.parents[j]] if j else 0.0)
        lines.append(f"{ind}{'ROOT' if j == 0 else 'JOINT'} {skel.joint_names[j]}")
        lines.append(f"{ind}{{")
        lines.append(f"{ind}  OFFSET {off[0]:.6f} {off[1]:.6f} {off[2]:.6f}")
        lines.append(f"{ind}  CHANNELS " + ("6 Xposition Yposition Zposition " if j == 0 else "3 ")
                     + "Zrotation Yrotation Xrotation")
        for c in children.get(j, []):
            emit(c, depth + 1)
        if not children.get(j):
            lines.extend([f"{ind}  End Site", f"{ind}  {{", f"{ind}    OFFSET 0.000000 0.000000 0.000000",
                          f"{ind}  }}"])
        lines.append(f"{ind}}}")

    emit(0, 0)
    angles = _zyx_degrees(local)  # [frames, joints, 3]
    lines += ["MOTION", f"Frames: {sm.num_frames}", f"Frame Time: {1.0 / sm.fps:.8f}"]
    for f in range(sm.num_frames):
        vals = np.concatenate([root[f], angles[f, order].ravel()])
        lines.append(" ".join(f"{v:.6f}" for v in vals))
    return "\n".join(lines) + "\n"


def write_bvh(path: str | Path, sm: SkeletonMotion, units_per_metre: float = 100.0) -> Path:
    """Write `bvh_text(sm)` atomically."""
    from avatarctl.atomic import write_text

    return write_text(path, bvh_text(sm, units_per_metre))
