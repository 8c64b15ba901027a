"""ActorsHQ captures (HumanRF, Işık et al. 2023): 160 cameras, released at full resolution (1x) and down-sampled by
2 and 4 (2x, 4x).

Layout, as the release's own loader reads it (the `actorshq` package of synthesiaresearch/humanrf at commit
c0c1fb7bc1c86cbb3b5905a5c68cebb9d66e4d31: ``actorshq/dataset/volumetric_dataset.py`` (`VolumetricDatasetFilepaths`),
``camera_data.py`` (`read_calibration_csv`, `CameraData`), ``download_manager.py``)::

    ActorXX/SequenceY/                      the sequence folder
      scene.json                            {"num_frames": N, ...}                       (not read)
      aabbs.csv, occupancy_grids/           per-frame boxes and occupancy                (not read)
      meshes.abc.xz                         per-frame meshes, Alembic                    (not read: below)
      Nx/                                   the scale folder: 1x, 2x or 4x
        calibration.csv                     one row per camera: name,w,h,rx,ry,rz,tx,ty,tz,fx,fy,px,py
        rgbs/CamXXX/CamXXX_rgb%06d.jpg      frames (CamXXX = Cam001 ... Cam160; frame number 0-based)
        masks/CamXXX/CamXXX_mask%06d.png    masks (gray > 127 foreground)
        light_annotations.csv               light-source circles per camera               (not read)

`avatarctl ingest` takes the scale folder (``.../Sequence1/4x``) or the sequence folder when it holds exactly one
scale folder.

calibration.csv (the quirks): ``rx ry rz`` is the axis-angle of the camera-to-WORLD rotation and ``tx ty tz`` the
camera centre in world metres (world = R_c2w · camera + t); the intrinsics are NORMALISED by the image size:
fx_px = fx · w, fy_px = fy · h, cx_px = px · w, cy_px = py · h (`CameraData.intrinsic_matrix`). The CSV is
written per scale folder with that folder's w, h. It carries no distortion columns: the released images are
treated as pinhole (``k1 k2 k3`` columns, when a CSV has them, are read as OpenCV radial terms).

Body fits: the release ships none. Ingest estimates them (``--fits keypoints``), or reads your own fits in the
capture's world frame beside the scale folder or in it: ``motion.npz`` (avatarctl `BodyMotion`) or EasyMocap
``smpl/%06d.json`` (e.g. converted from PhysAvatar's SMPL-X fits) -- looked for in the scale folder, then the
sequence folder.

Ground-truth geometry: ``meshes.abc.xz`` is one surface of body and clothes together (no garment / body split,
which ``eval --region garment`` needs) in a format avatarctl does not read (Alembic); it is not used.
"""

from __future__ import annotations

import csv
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from avatarctl.errors import InputError
from avatarctl.geometry.cameras import Camera
from avatarctl.io.capture import CaptureSource, FileMasks, make_camera, read_image_file

CALIBRATION = "calibration.csv"
COLUMNS = ("name", "w", "h", "rx", "ry", "rz", "tx", "ty", "tz", "fx", "fy", "px", "py")
NUM_CAMERAS = 160  # the release's rig (Cam001 ... Cam160)
_SCALE_DIR = re.compile(r"^([1-9][0-9]?)x$")
_SEQUENCE = re.compile(r"^Actor\d+$"), re.compile(r"^Sequence\d+$")


def rgb_path(scale_dir: Path, cam: str, frame: int) -> Path:
    """Where the release keeps camera `cam`'s frame `frame` (0-based) in a scale folder."""
    return Path(scale_dir) / "rgbs" / cam / f"{cam}_rgb{frame:06d}.jpg"


def mask_path(scale_dir: Path, cam: str, frame: int) -> Path:
    return Path(scale_dir) / "masks" / cam / f"{cam}_mask{frame:06d}.png"


def scale_folders(sequence_dir: Path) -> list[Path]:
    """The scale folders (``1x``, ``2x``, ``4x``, ...) of a sequence folder that hold a calibration.csv."""
    d = Path(sequence_dir)
    if not d.is_dir():
        return []
    return sorted((p for p in d.iterdir() if _SCALE_DIR.match(p.name) and (p / CALIBRATION).is_file()),
                  key=lambda p: int(p.name[:-1]))


def is_actorshq(root: Path) -> bool:
    """Whether `root` is an ActorsHQ scale folder (calibration.csv + rgbs/) or a sequence folder holding one."""
    root = Path(root)
    return ((root / CALIBRATION).is_file() and (root / "rgbs").is_dir()) or bool(scale_folders(root))


def resolve_scale_folder(root: Path) -> Path:
    """The scale folder of a capture path (the folder itself, or the single scale folder of a sequence folder)."""
    root = Path(root)
    if (root / CALIBRATION).is_file():
        return root
    found = scale_folders(root)
    if not found:
        raise InputError(f"no {CALIBRATION} (ActorsHQ)", where=str(root),
                         fix="pass the scale folder, e.g. Actor01/Sequence1/4x, which holds calibration.csv, rgbs/ "
                             "and masks/")
    if len(found) > 1:
        names = ", ".join(p.name for p in found)
        raise InputError(f"the sequence folder holds several scales ({names})", where=str(root),
                         fix=f"pass one of them, e.g. {found[-1]}")
    return found[0]


def release_scale(scale_dir: Path) -> float:
    """Scale of a scale folder's images relative to the full-resolution release: ``4x`` -> 0.25 (1.0 when the folder
    is not named like the release's)."""
    m = _SCALE_DIR.match(Path(scale_dir).name)
    return 1.0 / int(m.group(1)) if m else 1.0


def sequence_name(scale_dir: Path) -> str:
    """``ActorXX/SequenceY`` when the folders above the scale folder are named as in the release, else ""."""
    seq = Path(scale_dir).resolve().parent
    if _SEQUENCE[0].match(seq.parent.name) and _SEQUENCE[1].match(seq.name):
        return f"{seq.parent.name}/{seq.name}"
    return ""


def _rotvec_to_matrix(r: np.ndarray) -> np.ndarray:
    """[3] axis-angle (radians) -> [3, 3] rotation (Rodrigues)."""
    theta = float(np.linalg.norm(r))
    if theta < 1e-12:
        return np.eye(3)
    k = r / theta
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(theta) * kx + (1.0 - np.cos(theta)) * kx @ kx


def read_actorshq_cameras(path: Path) -> list[Camera]:
    """Cameras of a calibration.csv, converted to avatarctl's convention (OpenCV world->camera, pixels, metres)."""
    path = Path(path)
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            reader = csv.DictReader(fh)
            header = [c.strip() for c in (reader.fieldnames or [])]
            rows = list(reader)
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise InputError(f"cannot read {CALIBRATION} ({type(e).__name__})", where=str(path),
                         fix="re-download it") from None
    missing = [c for c in COLUMNS if c not in header]
    if missing:
        raise InputError(f"{CALIBRATION} lacks the column(s) {', '.join(missing)}", where=str(path),
                         fix=f"expected the header {','.join(COLUMNS)}")
    if not rows:
        raise InputError(f"{CALIBRATION} lists no cameras", where=str(path), fix="re-download it")
    cams = []
    for i, row in enumerate(rows, start=2):  # line numbers as an editor shows them (1 is the header)
        row = {k.strip(): (v or "").strip() for k, v in row.items() if k is not None}
        name = row["name"]
        try:
            w, h = int(row["w"]), int(row["h"])
            v = {c: float(row[c]) for c in COLUMNS[3:]}
            k = [float(row[c]) if row.get(c) else 0.0 for c in ("k1", "k2", "k3")]
        except ValueError:
            raise InputError(f"{CALIBRATION} line {i} (camera {name or '?'}) has a non-numeric value",
                             where=str(path), fix="re-download it") from None
        if not re.fullmatch(r"[A-Za-z0-9._-]+", name):
            raise InputError(f"{CALIBRATION} line {i}: camera name {name!r} is not a folder name", where=str(path),
                             fix="the release names its cameras Cam001 ... Cam160")
        r_c2w = _rotvec_to_matrix(np.array([v["rx"], v["ry"], v["rz"]]))
        centre = np.array([v["tx"], v["ty"], v["tz"]])
        K = np.array([[v["fx"] * w, 0.0, v["px"] * w], [0.0, v["fy"] * h, v["py"] * h], [0.0, 0.0, 1.0]])
        cams.append(make_camera(path, name=name, K=K, R=r_c2w.T, T=-r_c2w.T @ centre, width=w, height=h,
                                dist=np.array([k[0], k[1], 0.0, 0.0, k[2]])))
    names = [c.name for c in cams]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise InputError(f"{CALIBRATION} lists camera(s) {', '.join(dup)} twice", where=str(path),
                         fix="re-download it")
    return cams


def write_actorshq_cameras(path: Path, cameras: list[Camera]) -> None:
    """Write pinhole `cameras` as an ActorsHQ calibration.csv (the inverse of `read_actorshq_cameras`; synthetic
    captures in the release's layout: tests, benchmarks)."""
    from avatarctl.atomic import write_text

    lines = [",".join(COLUMNS)]
    for c in cameras:
        r_c2w = np.asarray(c.R, np.float64).T
        centre = -r_c2w @ np.asarray(c.T, np.float64)
        rvec = _matrix_to_rotvec(r_c2w)
        K = np.asarray(c.K, np.float64)
        vals = [c.width, c.height, *rvec, *centre, K[0, 0] / c.width, K[1, 1] / c.height, K[0, 2] / c.width,
                K[1, 2] / c.height]
        lines.append(",".join([c.name] + [repr(float(x)) if i > 1 else str(int(x)) for i, x in enumerate(vals)]))
    write_text(Path(path), "\n".join(lines) + "\n")


def _matrix_to_rotvec(R: np.ndarray) -> np.ndarray:
    """[3, 3] rotation -> [3] axis-angle (cv2.Rodrigues)."""
    import cv2

    return cv2.Rodrigues(np.ascontiguousarray(R, np.float64))[0].ravel()


def _scan(folder: Path, cam: str, kind: str, suffix: str) -> set[int]:
    """The frame numbers of the release's ``<cam>_<kind>%06d.<suffix>`` files in `folder`."""
    pat = re.compile(rf"^{re.escape(cam)}_{kind}(\d{{6}})\.{suffix}$")
    if not folder.is_dir():
        return set()
    return {int(m.group(1)) for m in map(pat.match, (p.name for p in folder.iterdir())) if m}


@dataclass(frozen=True)
class ReleaseImages:
    """The frames of a scale folder, located by the release's naming (no per-file index: 160 cameras x thousands of
    frames stay a rule, not a table)."""

    scale_dir: Path

    def read(self, cam: str, frame: int) -> np.ndarray:
        return read_image_file(rgb_path(self.scale_dir, cam, frame), cam, frame)

    def where(self, cam: str, frame: int) -> str:
        return str(rgb_path(self.scale_dir, cam, frame))


@dataclass(frozen=True)
class ReleaseMasks:
    """The masks of a scale folder (foreground > 127), located by the release's naming."""

    scale_dir: Path

    def read(self, cam: str, frame: int) -> np.ndarray:
        return FileMasks({(cam, frame): mask_path(self.scale_dir, cam, frame)}).read(cam, frame)

    def where(self, cam: str, frame: int) -> str:
        return str(mask_path(self.scale_dir, cam, frame))


def read_actorshq(root: Path) -> CaptureSource:
    """The capture at `root` (a scale folder, or a sequence folder with one) as a `CaptureSource`."""
    from avatarctl.io.easymocap_fits import has_capture_fits, read_capture_fits

    scale_dir = resolve_scale_folder(Path(root))
    cameras = read_actorshq_cameras(scale_dir / CALIBRATION)
    names = [c.name for c in cameras]
    if not (scale_dir / "rgbs").is_dir():
        raise InputError("no rgbs/ folder (ActorsHQ frames)", where=str(scale_dir),
                         fix="download the RGB frames (rgbs/CamXXX/CamXXX_rgb%06d.jpg) into this scale folder")
    image_frames = {n: _scan(scale_dir / "rgbs" / n, n, "rgb", "jpg") for n in names}
    masks = mask_frames = None
    if (scale_dir / "masks").is_dir():
        mask_frames = {n: _scan(scale_dir / "masks" / n, n, "mask", "png") for n in names}
        masks = ReleaseMasks(scale_dir)
    uncal = sorted(p.name for p in (scale_dir / "rgbs").iterdir() if p.is_dir() and p.name not in names)
    fits, fits_where = None, ""
    for d in (scale_dir, scale_dir.parent):
        if has_capture_fits(d):
            fits, fits_where = read_capture_fits(d)
            break
    notes = []
    if scale_dir != Path(root):
        notes.append(f"scale folder {scale_dir.name}")
    if not _SCALE_DIR.match(scale_dir.name):
        notes.append(f"folder {scale_dir.name!r} is not named 1x / 2x / 4x: its images are taken as the "
                     "full-resolution release")
    if fits is None:
        notes.append("ActorsHQ ships no body fits: estimate them (--fits keypoints) or add motion.npz beside the "
                     "scale folder")
    return CaptureSource(format="actorshq", root=Path(root), cameras=cameras, image_frames=image_frames,
                         images=ReleaseImages(scale_dir), fits=fits, fits_where=fits_where, masks=masks,
                         mask_frames=mask_frames, uncalibrated=uncal, notes=notes,
                         sequence=sequence_name(scale_dir), release_scale=release_scale(scale_dir))
