"""4D-DRESS captures (Wang et al., CVPR 2024): one take of one outfit, with textured scans and their garment labels.

Layout followed: eth-ait/4d-dress at commit d1685e1 (`dataset/README.md`, `dataset/utility.py`,
`dataset/extract_garment.py`), cross-checked with MPMAvatar's loader (KAISTChangmin/MPMAvatar a01e2c1,
`scene/dress4d_dataset.py`)::

    CAPTURE = <subject>/<Inner|Outer>/<Take*>/
      basic_info.pkl                       {'scan_frames': ['00011', ...], 'rotation', 'offset', ...}
      Capture/cameras.pkl                  {'0004': {'intrinsics' [3, 3] pixels, 'extrinsics' [3, 4] world -> camera
                                           (OpenCV; extract_garment.py flips x, y for PyTorch3D), ...}, ...}
      Capture/<cam>/images/capture-f%05d.png   RGB 940 x 1280 (W x H), already undistorted (no distortion given)
      Capture/<cam>/masks/mask-f%05d.png       the scan's rendered silhouette, 0 / 255 (> 127 foreground)
      SMPLX/mesh-f%05d_smplx.pkl           {global_orient 3, body_pose 63, transl 3, betas 10, left/right_hand_pose
                                           45 (offsets from the hand mean: smplx flat_hand_mean=False), jaw_pose,
                                           leye_pose, reye_pose 3, expression 10}
      SMPL/mesh-f%05d_smpl.pkl             {global_orient 3, body_pose 69, transl 3, betas 10}
      Meshes_pkl/mesh-f%05d.pkl            the scan: {vertices [V, 3] metres, faces [T, 3], colors, normals, uvs}
      Semantic/labels/label-f%05d.pkl      {'scan_labels' [V]}: 0 skin, 1 hair, 2 shoe, 3 upper, 4 lower, 5 outer

The recording's name (`CaptureSource.sequence`, what `--benchmark` protocols tell takes apart by) is read from the
folders: ``00170/Inner/Take1`` (the subject folder may carry the archive's ``_Inner`` / ``_Outer`` suffix, as in
``00170_Inner/Inner/Take1``); "" when they are named otherwise.

Cameras, scans and fits share the capture's world frame (`basic_info['rotation']` only turns the scan to face a
viewer; it is not applied). Frame number = the file number (`capture-f00011.png` -> 11). Fits: SMPL-X when
`SMPLX/` holds them, else SMPL. Every pickle is read with `avatarctl.safe_pickle` (numpy arrays and plain containers;
anything else is refused before it runs). The scans are the capture's ground-truth geometry for `eval --region
garment|body` (`ScanGeometry`, read one frame at a time): garment = upper, lower and outer.
"""

from __future__ import annotations

import functools
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from avatarctl.body.motion import BodyMotion
from avatarctl.errors import InputError
from avatarctl.geometry.cameras import Camera
from avatarctl.io.capture import (CaptureSource, FileImages, FileMasks, first_image_sizes, fmt_list, make_camera,
                                  safe_camera_name)
from avatarctl.io.gt_geometry import FrameGeometry
from avatarctl.safe_pickle import load_pickle

SURFACE_LABELS = ("skin", "hair", "shoe", "upper", "lower", "outer")
GARMENT_LABELS = (3, 4, 5)  # upper, lower, outer
CAMERAS_PKL = Path("Capture") / "cameras.pkl"
BASIC_INFO = "basic_info.pkl"
_IMAGE = re.compile(r"^capture-f(\d+)\.png$")
_MASK = re.compile(r"^mask-f(\d+)\.png$")
_SEQUENCE = re.compile(r"^(\d{5})(?:_(?:Inner|Outer))?$"), re.compile(r"^(?:Inner|Outer)$"), re.compile(r"^Take\d+$")
_SMPLX_KEYS = {"global_orient": 3, "body_pose": 63, "transl": 3, "jaw_pose": 3, "leye_pose": 3, "reye_pose": 3,
               "left_hand_pose": 45, "right_hand_pose": 45}
_SMPL_KEYS = {"global_orient": 3, "body_pose": 69, "transl": 3}


def is_four_d_dress(root: Path) -> bool:
    """A 4D-DRESS take folder: `Capture/cameras.pkl` and `basic_info.pkl`."""
    return (Path(root) / CAMERAS_PKL).is_file() and (Path(root) / BASIC_INFO).is_file()


def sequence_name(root: Path) -> str:
    """``<subject>/<Inner|Outer>/<TakeN>`` of a take folder named as in the release, else ""."""
    take = Path(root).resolve()
    subject, outfit = take.parent.parent.name, take.parent.name
    m = _SEQUENCE[0].match(subject)
    if m and _SEQUENCE[1].match(outfit) and _SEQUENCE[2].match(take.name):
        return f"{m.group(1)}/{outfit}/{take.name}"
    return ""


def _scan(folder: Path, pattern: re.Pattern) -> dict[int, Path]:
    out: dict[int, Path] = {}
    if folder.is_dir():
        for p in folder.iterdir():
            m = pattern.match(p.name)
            if m and p.is_file():
                out[int(m.group(1))] = p
    return out


def read_four_d_dress_cameras(path: Path, sizes: dict[str, tuple[int, int]]) -> list[Camera]:
    """Cameras of `Capture/cameras.pkl` that have images (`sizes`: name -> (W, H) of their first image)."""
    d = load_pickle(path, "cameras.pkl")
    if not isinstance(d, dict) or not d:
        raise InputError("cameras.pkl holds no cameras", where=str(path),
                         fix="expected {'0004': {'intrinsics': 3x3, 'extrinsics': 3x4}, ...}")
    cams = []
    for cid in sorted(d, key=str):
        name = safe_camera_name(str(cid))
        if name not in sizes:
            continue
        entry = d[cid]
        try:
            K = np.asarray(entry["intrinsics"], dtype=np.float64).reshape(3, 3)
            E = np.asarray(entry["extrinsics"], dtype=np.float64).reshape(-1, 4)[:3]
        except (KeyError, TypeError, ValueError):
            raise InputError(f"camera {cid}: no 3x3 'intrinsics' and 3x4 'extrinsics'", where=str(path),
                             fix="re-download Capture/cameras.pkl") from None
        W, H = sizes[name]
        cams.append(make_camera(path, name=name, K=K, R=E[:, :3], T=E[:, 3], width=W, height=H, dist=np.zeros(5)))
    return cams


def _frames_of_basic_info(path: Path) -> list[int] | None:
    info = load_pickle(path, BASIC_INFO)
    if not isinstance(info, dict) or "scan_frames" not in info:
        raise InputError("basic_info.pkl has no 'scan_frames'", where=str(path), fix="re-download basic_info.pkl")
    try:
        return sorted(int(str(f)) for f in info["scan_frames"])
    except (TypeError, ValueError):
        raise InputError("basic_info.pkl 'scan_frames' are not frame numbers", where=str(path),
                         fix="re-download basic_info.pkl") from None


def _rows(d: dict, key: str, dim: int, where: Path) -> np.ndarray:
    try:
        a = np.asarray(d[key], dtype=np.float64).reshape(-1)
    except KeyError:
        raise InputError(f"fit has no {key!r}", where=str(where), fix="re-download the fit file") from None
    except (TypeError, ValueError):
        raise InputError(f"fit {key!r} is not numeric", where=str(where), fix="re-download the fit file") from None
    if a.size != dim:
        raise InputError(f"fit {key} has {a.size} values, expected {dim}", where=str(where),
                         fix="re-download the fit file")
    if not np.isfinite(a).all():
        raise InputError(f"fit {key} contains NaN or inf", where=str(where), fix="re-download the fit file")
    return a


def read_four_d_dress_fits(root: Path, frames: list[int]) -> tuple[BodyMotion, str]:
    """SMPL-X fits of `frames` (or SMPL when SMPLX/ is absent) -> (BodyMotion, the folder read). Frames without a fit
    file are left out of the motion (ingest reports them)."""
    root = Path(root)
    kind, folder, suffix, keys = ("smplx", root / "SMPLX", "_smplx.pkl", _SMPLX_KEYS) \
        if any((root / "SMPLX").glob("mesh-f*_smplx.pkl")) else ("smpl", root / "SMPL", "_smpl.pkl", _SMPL_KEYS)
    if not folder.is_dir():
        raise InputError("no body fits (SMPLX/ or SMPL/)", where=str(root),
                         fix="4D-DRESS takes ship SMPLX/mesh-f%05d_smplx.pkl; or estimate fits with --fits keypoints")
    rows: dict[str, list[np.ndarray]] = {k: [] for k in keys}
    extra: dict[str, list[np.ndarray]] = {"betas": [], "expression": []}
    have = []
    for f in frames:
        p = folder / f"mesh-f{f:05d}{suffix}"
        if not p.is_file():
            continue
        d = load_pickle(p, "fit file")
        if not isinstance(d, dict):
            raise InputError("fit file is not a dict of parameters", where=str(p), fix="re-download it")
        for k, dim in keys.items():
            rows[k].append(_rows(d, k, dim, p))
        extra["betas"].append(np.asarray(d.get("betas", np.zeros(10)), dtype=np.float64).reshape(-1))
        if kind == "smplx" and "expression" in d:
            extra["expression"].append(np.asarray(d["expression"], dtype=np.float64).reshape(-1))
        have.append(f)
    if not have:
        raise InputError(f"no {kind.upper()} fit for any of the {len(frames)} frames", where=str(folder),
                         fix=f"expected {folder.name}/mesh-f%05d{suffix} per frame")
    if len({b.size for b in extra["betas"]}) != 1:
        raise InputError("the fits' betas differ in length", where=str(folder), fix="re-download the fits")
    expr = np.stack(extra["expression"]) if len(extra["expression"]) == len(have) and have and kind == "smplx" \
        else None
    motion = BodyMotion(body_model=kind, frame_index=np.asarray(have), betas=np.stack(extra["betas"]).mean(0),
                        expression=expr, **{k: np.stack(v) for k, v in rows.items()})
    return motion, str(folder)


def read_four_d_dress(root: Path) -> CaptureSource:
    root = Path(root)
    capture = root / "Capture"
    if not (root / CAMERAS_PKL).is_file():
        raise InputError("Capture/cameras.pkl missing", where=str(root),
                         fix="pass a 4D-DRESS take folder (<subject>/<Inner|Outer>/<Take*>) with its Capture/ folder")
    scan_frames = _frames_of_basic_info(root / BASIC_INFO) if (root / BASIC_INFO).is_file() else None
    per_cam = {safe_camera_name(d.name): _scan(d / "images", _IMAGE) for d in sorted(capture.iterdir())
               if d.is_dir()}
    sizes = first_image_sizes(per_cam)
    cameras = read_four_d_dress_cameras(root / CAMERAS_PKL, sizes)
    if not cameras:
        raise InputError("no camera of cameras.pkl has images (Capture/<cam>/images/capture-f%05d.png)",
                         where=str(capture), fix="download the take's Capture/ images")
    names = [c.name for c in cameras]
    keep = (lambda f: f in set(scan_frames)) if scan_frames is not None else (lambda f: True)
    images = {(c, f): p for c, d in per_cam.items() for f, p in d.items() if keep(f)}
    image_frames = {n: {f for (c, f) in images if c == n} for n in names}
    masks = {(safe_camera_name(d.name), f): p for d in capture.iterdir() if d.is_dir()
             for f, p in _scan(d / "masks", _MASK).items() if keep(f)}
    mask_frames = {n: {f for (c, f) in masks if c == n} for n in names}
    frames = sorted(set().union(*image_frames.values()))
    fits, fits_where = read_four_d_dress_fits(root, frames) if frames else (None, "")
    notes = [f"{len(cameras)} cameras from Capture/cameras.pkl (no lens distortion)"]
    if fits is not None:
        notes.append(f"{fits.body_model.upper()} fits from {Path(fits_where).name}/")
        if fits.body_model == "smplx":
            notes.append("SMPL-X hand poses are offsets from the model's hand mean (smplx flat_hand_mean=False): "
                         "ingest adds the model file's mean")
    if scan_frames is not None:
        dropped = sorted({f for d in per_cam.values() for f in d} - set(scan_frames))
        if dropped:
            notes.append(f"images of frames {fmt_list(dropped)} are not scan frames (basic_info.pkl): left out")
    has_masks = any(mask_frames.values())
    return CaptureSource(format="4d_dress", root=root, cameras=cameras, image_frames=image_frames,
                         images=FileImages(images), fits=fits, fits_where=fits_where,
                         masks=FileMasks(masks) if has_masks else None, mask_frames=mask_frames if has_masks else None,
                         uncalibrated=sorted({c for c, d in per_cam.items() if d} - set(names)),
                         notes=notes, hands_from_mean=fits is not None and fits.body_model == "smplx",
                         sequence=sequence_name(root))


# --- ground-truth geometry: the labelled scans -------------------------------------------------------------------
def has_scan_geometry(root: Path) -> bool:
    """The take ships scans and their labels (`Meshes_pkl/`, `Semantic/labels/`)."""
    root = Path(root)
    return is_four_d_dress(root) and (root / "Meshes_pkl").is_dir() and (root / "Semantic" / "labels").is_dir()


@dataclass(frozen=True)
class ScanGeometry:
    """The per-frame labelled scans of a 4D-DRESS take as ground-truth geometry (`io.gt_geometry`'s `frame`
    interface): each frame read when asked (a scan is ~80k faces; a take holds ~150)."""

    root: Path

    @property
    def path(self) -> Path:
        return self.root / "Meshes_pkl"

    def frame(self, frame: int) -> FrameGeometry:
        """The scan of capture frame `frame` split by its vertex labels: a face is garment when at least two of its
        vertices are labelled upper, lower or outer; the rest (skin, hair, shoes) is body. The last two frames read
        are kept (eval asks for every view of a frame in turn)."""
        return _labelled_scan(self.root, int(frame))


@functools.lru_cache(maxsize=2)
def _labelled_scan(root: Path, frame: int) -> FrameGeometry:
    """`ScanGeometry.frame` of the take at `root`."""
    mp = root / "Meshes_pkl" / f"mesh-f{int(frame):05d}.pkl"
    lp = root / "Semantic" / "labels" / f"label-f{int(frame):05d}.pkl"
    for p in (mp, lp):
        if not p.is_file():
            raise InputError(f"frame {frame} has no labelled scan", where=str(p),
                             fix="score only frames the take has scans for (--frames)")
    mesh, labels = load_pickle(mp, "scan mesh"), load_pickle(lp, "scan labels")
    try:
        v = np.asarray(mesh["vertices"], dtype=np.float32).reshape(-1, 3)
        f = np.asarray(mesh["faces"], dtype=np.int64).reshape(-1, 3)
        lab = np.asarray(labels["scan_labels"]).reshape(-1)
    except (KeyError, TypeError, ValueError):
        raise InputError("scan or label file lacks vertices / faces / scan_labels", where=str(mp),
                         fix="re-download Meshes_pkl/ and Semantic/labels/") from None
    if len(lab) != len(v) or (f.size and (f.min() < 0 or f.max() >= len(v))) or not np.isfinite(v).all():
        raise InputError(f"scan has {len(v)} vertices but {len(lab)} labels (or bad faces)", where=str(lp),
                         fix="use the label file of this scan")
    garment_face = np.isin(lab, GARMENT_LABELS)[f].sum(axis=1) >= 2  # [T]
    return FrameGeometry(body_vertices=v, body_faces=f[~garment_face], garment_vertices=v,
                         garment_faces=f[garment_face])
