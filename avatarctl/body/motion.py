"""`BodyMotion`: body-model fits for a sequence of frames, in one internal representation per body model.

- anny: `pose_parameters` [frames, 104, 4, 4] (anny "local-ref" deltas, exactly as passed to `anny.Anny()`;
  the root delta is the root's world pose), `phenotype` [P] with `phenotype_labels`.
- toy (tests): `global_orient`, `body_pose`, `transl` [frames, 3] (see avatarctl.body.toy).
- smpl / smplx: `global_orient` [frames, 3], `body_pose` [frames, 69 (smpl) | 63 (smplx)], `transl` [frames, 3]
  (the SMPL/SMPL-X package convention: rotation about the pelvis joint, then translation), `betas` [B];
  smplx also `jaw_pose`, `leye_pose`, `reye_pose` [frames, 3], `left_hand_pose`, `right_hand_pose`
  [frames, 45] (full axis-angle, no PCA), `expression` [frames, E].

Stored as `.npz` (no pickles) with `body_model`, `frame_index`, `fps` beside the arrays.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from pathlib import Path

import numpy as np

from avatarctl.errors import InputError

BODY_MODELS = ("anny", "smpl", "smplx", "toy")
_BODY_POSE_DIM = {"smpl": 69, "smplx": 63, "toy": 3}  # toy: joint 1 of the sphere body (avatarctl.body.toy)
_PER_FRAME = ("pose_parameters", "global_orient", "body_pose", "transl", "jaw_pose", "leye_pose", "reye_pose",
              "left_hand_pose", "right_hand_pose", "expression")


@dataclass(frozen=True)
class BodyMotion:
    body_model: str
    frame_index: np.ndarray  # [frames] int64, the capture's frame numbers
    fps: float = 30.0
    # anny
    pose_parameters: np.ndarray | None = None  # [frames, 104, 4, 4]
    phenotype: np.ndarray | None = None  # [P]
    phenotype_labels: tuple[str, ...] = ()
    # smpl / smplx
    global_orient: np.ndarray | None = None  # [frames, 3]
    body_pose: np.ndarray | None = None  # [frames, 69 | 63]
    transl: np.ndarray | None = None  # [frames, 3]
    betas: np.ndarray | None = None  # [B]
    jaw_pose: np.ndarray | None = None
    leye_pose: np.ndarray | None = None
    reye_pose: np.ndarray | None = None
    left_hand_pose: np.ndarray | None = None
    right_hand_pose: np.ndarray | None = None
    expression: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.body_model not in BODY_MODELS:
            raise ValueError(f"unknown body model {self.body_model!r}; expected one of {BODY_MODELS}")
        fi = np.asarray(self.frame_index, dtype=np.int64).ravel()
        object.__setattr__(self, "frame_index", fi)
        n = fi.shape[0]
        for name in _PER_FRAME:
            a = getattr(self, name)
            if a is not None:
                a = np.asarray(a, dtype=np.float32)
                object.__setattr__(self, name, a)
                if a.shape[0] != n:
                    raise ValueError(f"{name} has {a.shape[0]} frames but frame_index has {n}")
                if not np.isfinite(a).all():
                    row = int(np.argwhere(~np.isfinite(a.reshape(n, -1)))[0, 0])
                    raise ValueError(f"{name} contains non-finite values (first in frame row {row})")
        for name in ("phenotype", "betas"):
            a = getattr(self, name)
            if a is not None:
                object.__setattr__(self, name, np.asarray(a, dtype=np.float32).ravel())
        if self.body_model == "anny":
            if self.pose_parameters is None or self.pose_parameters.shape[1:] != (104, 4, 4):
                shape = None if self.pose_parameters is None else self.pose_parameters.shape
                raise ValueError(f"anny motion needs pose_parameters [frames, 104, 4, 4], got {shape}")
        else:
            want = _BODY_POSE_DIM[self.body_model]
            for name, dim in (("global_orient", 3), ("transl", 3), ("body_pose", want)):
                a = getattr(self, name)
                if a is None or a.ndim != 2 or a.shape[1] != dim:
                    raise ValueError(f"{self.body_model} motion needs {name} [frames, {dim}], got "
                                     f"{None if a is None else a.shape}")

    @property
    def num_frames(self) -> int:
        return int(self.frame_index.shape[0])

    def select(self, idx: np.ndarray | list[int] | slice) -> "BodyMotion":
        """The motion restricted to rows `idx` (positions, not frame numbers: `for_frames` takes those)."""
        kw = {name: getattr(self, name)[idx] for name in _PER_FRAME if getattr(self, name) is not None}
        return replace(self, frame_index=self.frame_index[idx], **kw)

    def for_frames(self, frames: list[int] | np.ndarray) -> "BodyMotion":
        """The motion of capture frame numbers `frames`, in their order (`select` of `rows_for`); raises KeyError
        naming a missing frame."""
        return self.select(self.rows_for(frames))

    def rows_for(self, frames: list[int] | np.ndarray) -> np.ndarray:
        """Row positions of capture frame numbers `frames`; raises KeyError naming a missing frame."""
        lookup = {int(f): i for i, f in enumerate(self.frame_index)}
        try:
            return np.array([lookup[int(f)] for f in frames], dtype=np.int64)
        except KeyError as e:
            raise KeyError(f"frame {e.args[0]} has no body fit") from None

    def to_npz_dict(self) -> dict[str, np.ndarray]:
        out: dict[str, np.ndarray] = {"body_model": np.array(self.body_model), "fps": np.array(self.fps)}
        for f in fields(self):
            if f.name in ("body_model", "fps"):
                continue
            v = getattr(self, f.name)
            if v is None or (isinstance(v, tuple) and not v):
                continue
            out[f.name] = np.array(v)
        return out

    def save(self, path: str | Path, extra: dict[str, np.ndarray] | None = None) -> None:
        """Write the npz atomically; `extra` arrays (e.g. provenance) are stored beside and ignored by `load`."""
        from avatarctl.atomic import atomic_path

        arrays = self.to_npz_dict()
        clash = set(arrays) & set(extra or {})
        assert not clash, f"extra arrays would overwrite {sorted(clash)}"
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as fh:
                np.savez(fh, **arrays, **(extra or {}))

    @classmethod
    def load(cls, path: str | Path) -> "BodyMotion":
        """Read a `save`d npz (never pickles); a one-line `InputError` naming the file when it is unreadable, cut
        off, or fails the checks of `__post_init__` (non-finite values, wrong shapes, unknown body model)."""
        import zipfile

        try:
            with np.load(path, allow_pickle=False) as z:
                kw = {k: z[k] for k in z.files}
            kw["body_model"] = str(kw["body_model"])
            kw["fps"] = float(kw.get("fps", 30.0))
            if "phenotype_labels" in kw:
                kw["phenotype_labels"] = tuple(str(s) for s in kw["phenotype_labels"])
            names = {f.name for f in fields(cls)}
            return cls(**{k: v for k, v in kw.items() if k in names})
        except (ValueError, KeyError, OSError, EOFError, TypeError, zipfile.BadZipFile) as e:
            msg = " ".join(str(e).split())[:200] or type(e).__name__
            raise InputError(f"bad body fits: {msg}", where=str(path),
                             fix="write it with avatarctl.body.motion.BodyMotion.save (finite values, one row per "
                                 "frame, anny pose_parameters [frames, 104, 4, 4] or SMPL arrays)") from None
