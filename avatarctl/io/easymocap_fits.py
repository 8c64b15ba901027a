"""Body fits shipped with a capture: EasyMocap ``smpl/%06d.json`` (Rh/Th convention) and ``motion.npz``
(`BodyMotion`, what `avatarctl synth` writes).

EasyMocap json: a list of people ``[{id, Rh (1,3), Th (1,3), poses (1,72), shapes (1,10)}, ...]`` or the newer
``{"annots": [...]}`` wrapper. The person with the smallest ``id`` is used. ``Rh``/``Th`` rotate about the world
origin then translate (metres); see `avatarctl.io.capture.RhThFits`.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from avatarctl.body.motion import BodyMotion
from avatarctl.errors import InputError
from avatarctl.io.capture import RhThFits

SMPL_POSE_DIM = 72


def as_vector(value, n: int, name: str, where: str) -> np.ndarray:
    """A fit entry as a finite float64 [n] vector; shapes (1, n) and (n,) are accepted."""
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"fit entry {name} is not numeric", where=where, fix=f"{name} must hold {n} numbers") from None
    if a.size != n or (a.ndim == 2 and a.shape[0] != 1) or a.ndim > 2:
        raise InputError(f"fit entry {name} has shape {a.shape}, expected ({n},) or (1, {n})", where=where,
                         fix=f"write {name} with {n} values per frame")
    if not np.isfinite(a).all():
        raise InputError(f"fit entry {name} contains NaN or inf", where=where, fix="re-run the fitting for this frame")
    return a.reshape(n)


def rhth_from_records(records: list[tuple[int, dict, str]], where: str) -> RhThFits:
    """Stack per-frame dicts {Rh, Th, poses, shapes} (frame number, dict, file) into `RhThFits`."""
    if not records:
        raise InputError("no body fits found", where=where, fix="add one fit file per frame")
    records = sorted(records, key=lambda r: r[0])
    Rh, Th, poses, shapes = [], [], [], []
    for frame, d, f in records:
        for key in ("Rh", "Th", "poses", "shapes"):
            if key not in d:
                raise InputError(f"fit has no {key!r} entry", where=f, fix="write Rh, Th, poses and shapes per frame")
        p = np.asarray(d["poses"], dtype=np.float64)
        if p.size != SMPL_POSE_DIM:
            raise InputError(f"fit poses have {p.size} values; only SMPL fits ({SMPL_POSE_DIM} values) in the Rh/Th "
                             "convention are supported", where=f,
                             fix="fit with the SMPL model (EasyMocap --model smpl), or provide a motion.npz")
        Rh.append(as_vector(d["Rh"], 3, "Rh", f))
        Th.append(as_vector(d["Th"], 3, "Th", f))
        poses.append(as_vector(d["poses"], SMPL_POSE_DIM, "poses", f))
        s = np.asarray(d["shapes"], dtype=np.float64).reshape(-1)
        if s.size == 0 or not np.isfinite(s).all():
            raise InputError("fit shapes are empty or non-finite", where=f, fix="write shapes (1, 10) per frame")
        shapes.append(s)
    if len({s.size for s in shapes}) != 1:
        raise InputError("fits disagree on the number of shape coefficients", where=where,
                         fix="use the same shapes length in every frame")
    return RhThFits(kind="smpl", frame_index=np.array([r[0] for r in records], dtype=np.int64),
                    Rh=np.stack(Rh), Th=np.stack(Th), poses=np.stack(poses), shapes=np.mean(shapes, axis=0),
                    where=where)


def read_easymocap_smpl_dir(folder: Path) -> RhThFits:
    """``smpl/%06d.json`` -> `RhThFits` (frame number = file name)."""
    folder = Path(folder)
    records = []
    for p in sorted(folder.glob("*.json")):
        if not p.stem.isdigit():
            continue
        try:
            data = json.loads(p.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
            raise InputError(f"cannot parse fit file ({type(e).__name__})", where=str(p),
                             fix="re-export it; EasyMocap writes a JSON list of people") from None
        if isinstance(data, dict):
            data = data.get("annots", data.get("people"))
        if not isinstance(data, list) or not data or not all(isinstance(d, dict) for d in data):
            raise InputError("fit file holds no people", where=str(p),
                             fix="expected a list [{id, Rh, Th, poses, shapes}] or {\"annots\": [...]}")
        person = min(data, key=lambda d: int(d.get("id", 0)))
        records.append((int(p.stem), person, str(p)))
    return rhth_from_records(records, str(folder))


def has_capture_fits(root: Path) -> bool:
    """Whether a capture ships body fits (``motion.npz`` or ``smpl/``)."""
    return (Path(root) / "motion.npz").is_file() or (Path(root) / "smpl").is_dir()


def read_capture_fits(root: Path) -> tuple[BodyMotion | RhThFits, str]:
    """(fits, where) beside a capture: ``motion.npz`` (preferred) or EasyMocap ``smpl/*.json``."""
    root = Path(root)
    if (root / "motion.npz").is_file():
        return BodyMotion.load(root / "motion.npz"), str(root / "motion.npz")
    if (root / "smpl").is_dir():
        return read_easymocap_smpl_dir(root / "smpl"), str(root / "smpl")
    raise InputError("no body fits (motion.npz or smpl/*.json)", where=str(root),
                     fix="add motion.npz (avatarctl BodyMotion) or EasyMocap smpl/%06d.json fits")
