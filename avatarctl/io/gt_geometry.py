"""Ground-truth geometry a capture may carry: `gt/geometry.npz` (written by `avatarctl synth`), or the labelled
scans of a 4D-DRESS take (`avatarctl.io.four_d_dress.ScanGeometry`).

Keys read from `gt/geometry.npz` (others are ignored): `frame_index` [F] capture frame ids, `body_vertices`
[F, Vb, 3] and `garment_vertices` [F, Vg, 3] (world metres, the capture's calibration frame), `body_faces` [Fb, 3],
`garment_faces` [Fg, 3]. Used by `avatarctl eval --region` to score the garment and the rest of the body apart,
through `open_gt_geometry(capture_dir).frame(frame)` -> `FrameGeometry` (one frame's meshes; scans change topology
from frame to frame, so only the synth's fixed-topology file offers the stacked arrays).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np

from avatarctl.errors import InputError

GT_GEOMETRY = Path("gt") / "geometry.npz"  # relative to the capture folder
GT_MOTION = Path("gt") / "motion.npz"  # the true body fits, when the capture's motion.npz was written with noise
_KEYS = ("frame_index", "body_vertices", "garment_vertices", "body_faces", "garment_faces")


@dataclass(frozen=True)
class FrameGeometry:
    """One frame's body and garment meshes (world metres)."""

    body_vertices: np.ndarray  # [Vb, 3] float32
    body_faces: np.ndarray  # [Fb, 3] int
    garment_vertices: np.ndarray  # [Vg, 3] float32
    garment_faces: np.ndarray  # [Fg, 3] int


class GeometrySource(Protocol):
    """What `eval --region garment|body` needs of a capture's ground truth."""

    path: Path

    def frame(self, frame: int) -> FrameGeometry:
        """The meshes of capture frame `frame`; InputError when the ground truth does not cover it."""
        ...


@dataclass(frozen=True)
class GroundTruthGeometry:
    """Per-frame body and garment meshes of a capture."""

    frame_index: np.ndarray  # [F] int capture frame ids
    body_vertices: np.ndarray  # [F, Vb, 3] float32 world metres
    body_faces: np.ndarray  # [Fb, 3] int
    garment_vertices: np.ndarray  # [F, Vg, 3] float32 world metres
    garment_faces: np.ndarray  # [Fg, 3] int
    path: Path

    def row(self, frame: int) -> int:
        """Row of capture frame `frame` in the per-frame arrays."""
        hit = np.flatnonzero(self.frame_index == int(frame))
        if not len(hit):
            raise InputError(f"frame {frame} is not in the ground-truth geometry", where=str(self.path),
                             fix="score only frames the capture's gt/geometry.npz covers (--frames)")
        return int(hit[0])

    def frame(self, frame: int) -> FrameGeometry:
        r = self.row(frame)
        return FrameGeometry(body_vertices=self.body_vertices[r], body_faces=self.body_faces,
                             garment_vertices=self.garment_vertices[r], garment_faces=self.garment_faces)


def _synth_config(capture_dir: str | Path) -> dict | None:
    """The `avatarctl synth` config a capture's capture.json records, or None for any other capture (real, unreadable,
    or made by another generator)."""
    import json

    try:
        info = json.loads((Path(capture_dir) / "capture.json").read_text())
        cfg = info["config"]
        return cfg if str(info["generator"]).startswith("synth") and isinstance(cfg, dict) else None
    except (OSError, ValueError, KeyError, TypeError):
        return None


def fits_are_ground_truth(capture_dir: str | Path) -> bool:
    """True for a capture made by `avatarctl synth` with exact body fits (no `--fit-noise`, no `--fits none`): its
    motion.npz is the pose the images were rendered from. Any other capture (real, or synth with noisy or estimated
    fits) -> False."""
    cfg = _synth_config(capture_dir)
    return cfg is not None and not cfg.get("fit_noise_deg") and not cfg.get("fit_noise_cm") \
        and cfg.get("fits", "truth") == "truth"  # "fits": since issue 51


def masks_are_ground_truth(capture_dir: str | Path, masks: str | None) -> bool:
    """True when the masks a project was ingested with (`masks`: ingest's resolved mask source) are the files of a
    capture made by `avatarctl synth` with its true masks (no `--masks none`); estimated masks (MediaPipe, plates) or
    any other capture's -> False."""
    cfg = _synth_config(capture_dir) if masks == "files" else None
    return cfg is not None and cfg.get("masks", "truth") == "truth"


def find_gt_geometry(capture_dir: str | Path) -> Path | None:
    """The capture's ground-truth geometry file, or None when it carries none."""
    p = Path(capture_dir) / GT_GEOMETRY
    return p if p.is_file() else None


def open_gt_geometry(capture_dir: str | Path) -> GeometrySource | None:
    """The capture's ground-truth geometry: `gt/geometry.npz` (synth), else a 4D-DRESS take's labelled scans (read
    per frame); None when it carries neither."""
    path = find_gt_geometry(capture_dir)
    if path is not None:
        return load_gt_geometry(path)
    from avatarctl.io.four_d_dress import ScanGeometry, has_scan_geometry

    return ScanGeometry(Path(capture_dir)) if has_scan_geometry(capture_dir) else None


def load_gt_geometry(path: str | Path) -> GroundTruthGeometry:
    """Read and check `gt/geometry.npz`; a bad file is an `InputError` naming the key."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            missing = [k for k in _KEYS if k not in z.files]
            if missing:
                raise InputError(f"ground-truth geometry lacks {', '.join(missing)}", where=str(path),
                                 fix="re-create the capture with `avatarctl synth`")
            d = {k: np.asarray(z[k]) for k in _KEYS}
    except InputError:
        raise
    except (OSError, ValueError) as e:
        raise InputError(f"cannot read ground-truth geometry ({e})", where=str(path),
                         fix="re-create the capture with `avatarctl synth`") from None
    F = len(d["frame_index"])
    for name in ("body", "garment"):
        v, f = d[f"{name}_vertices"], d[f"{name}_faces"]
        if v.ndim != 3 or v.shape[0] != F or v.shape[2] != 3 or f.ndim != 2 or f.shape[1] != 3 \
                or (f.size and (f.min() < 0 or f.max() >= v.shape[1])) or not np.isfinite(v).all():
            raise InputError(f"{name}_vertices {v.shape} / {name}_faces {f.shape} are not {F} frames of a "
                             "finite triangle mesh", where=str(path), fix="re-create the capture with `avatarctl synth`")
    return GroundTruthGeometry(frame_index=d["frame_index"].astype(np.int64),
                               body_vertices=d["body_vertices"].astype(np.float32),
                               body_faces=d["body_faces"].astype(np.int64),
                               garment_vertices=d["garment_vertices"].astype(np.float32),
                               garment_faces=d["garment_faces"].astype(np.int64), path=path)
