"""What every capture reader returns: `CaptureSource`, a format-independent view of a raw capture.

A reader (``avatarctl/io/<format>.py``) only *describes* the capture: calibrated cameras (as calibrated, with
distortion), the frame numbers present in every camera, where each image / mask lives, and the body fits in the
format's own convention. It reads pixels lazily and never writes anything. The ingest pipeline
(``avatarctl/ingest/pipeline.py``) undistorts, converts and writes the project.

Conventions: cameras are OpenCV (world->camera, metres, ``dist = k1 k2 p1 p2 k3``); images are RGB uint8
[H, W, 3] in the *distorted* capture geometry; masks are bool [H, W] in the same geometry.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import numpy as np

from avatarctl.body.motion import BodyMotion
from avatarctl.errors import InputError
from avatarctl.io.project_io import Split
from avatarctl.geometry.cameras import Camera

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp")
_SAFE = re.compile(r"[^A-Za-z0-9._-]+")


def safe_camera_name(name: str) -> str:
    """Camera names become folder names in the project: 'Camera (3)' -> 'Camera_3'."""
    out = _SAFE.sub("_", name).strip("_")
    if not out:
        raise InputError(f"camera name {name!r} has no usable characters", fix="rename the camera folder")
    return out


@dataclass(frozen=True)
class RhThFits:
    """SMPL fits in the EasyMocap / ZJU-MoCap convention.

    Posed vertices are ``v = R(Rh) · SMPL(poses, shapes, transl=0) + Th``: ``Rh`` rotates about the world ORIGIN
    and ``Th`` translates afterwards (metres). This is not SMPL's ``global_orient``/``transl`` (a rotation about the
    pelvis joint); `avatarctl.ingest.fits.rhth_to_smpl` converts.
    """

    kind: str  # "smpl" (72 pose values)
    frame_index: np.ndarray  # [frames] int64 capture frame numbers
    Rh: np.ndarray  # [frames, 3] axis-angle, radians
    Th: np.ndarray  # [frames, 3] metres
    poses: np.ndarray  # [frames, 72] SMPL axis-angle; poses[:, :3] is a root rotation about the pelvis (usually 0)
    shapes: np.ndarray  # [B] betas (the per-frame shapes, averaged)
    where: str  # file or folder the fits came from (for error messages)

    @property
    def body_model(self) -> str:
        return self.kind


BodyFits = BodyMotion | RhThFits


class ImageReader(Protocol):
    def read(self, cam: str, frame: int) -> np.ndarray:
        """RGB uint8 [H, W, 3]; raises InputError naming the file when it is missing or unreadable."""
        ...

    def where(self, cam: str, frame: int) -> str:
        """Human-readable location (file path) of one image, for messages."""
        ...


class MaskReader(Protocol):
    def read(self, cam: str, frame: int) -> np.ndarray:
        """bool [H, W] foreground; raises InputError naming the file when it is missing or unreadable."""
        ...

    def where(self, cam: str, frame: int) -> str:
        ...


def make_camera(where: str | Path, **kw) -> Camera:
    """`Camera(**kw)` for a reader: the camera's own checks (finite values, R a rotation, 4-5 distortion
    coefficients, positive focal lengths and size) become a one-line `InputError` naming the calibration file."""
    try:
        return Camera(**kw)
    except ValueError as e:
        raise InputError(f"bad calibration: {e}", where=str(where),
                         fix="fix or re-export the calibration (OpenCV convention: world->camera R, T in metres, "
                             "dist k1 k2 p1 p2 k3)") from None


def read_image_file(path: Path, cam: str, frame: int) -> np.ndarray:
    """RGB uint8 [H, W, 3] from an image file, with a one-line error for missing / corrupt files."""
    import cv2

    if not path.is_file():
        raise InputError(f"image missing: camera {cam}, frame {frame}", where=str(path),
                         fix="add the image or leave the frame out with --frames")
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None or img.size == 0:
        raise InputError(f"image unreadable or corrupt: camera {cam}, frame {frame}", where=str(path),
                         fix="re-export this image, or leave the frame out with --frames")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


@dataclass(frozen=True)
class FileImages:
    """Images stored one file per (camera, frame)."""

    paths: dict[tuple[str, int], Path]

    def read(self, cam: str, frame: int) -> np.ndarray:
        return read_image_file(self.path(cam, frame), cam, frame)

    def path(self, cam: str, frame: int) -> Path:
        try:
            return self.paths[(cam, frame)]
        except KeyError:
            raise InputError(f"no image for camera {cam}, frame {frame}", fix="check --frames / --views") from None

    def where(self, cam: str, frame: int) -> str:
        return str(self.paths.get((cam, frame), f"camera {cam} frame {frame}"))


@dataclass(frozen=True)
class FileMasks:
    """Masks stored one file per (camera, frame); foreground = gray value > `threshold`."""

    paths: dict[tuple[str, int], Path]
    threshold: int = 127  # ZJU mask_cihp: > 0; THuman4 JPEG masks: > 128

    def read(self, cam: str, frame: int) -> np.ndarray:
        import cv2

        p = self.paths.get((cam, frame))
        if p is None or not p.is_file():
            raise InputError(f"mask missing: camera {cam}, frame {frame}", where=str(p) if p else None,
                             fix="add the mask, use --masks background, or leave the frame out with --frames")
        m = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        if m is None or m.size == 0:
            raise InputError(f"mask unreadable or corrupt: camera {cam}, frame {frame}", where=str(p),
                             fix="re-export this mask, or use --masks background")
        if m.ndim == 3:
            m = m[..., :3].max(axis=-1)
        return m > self.threshold

    def where(self, cam: str, frame: int) -> str:
        return str(self.paths.get((cam, frame), f"camera {cam} frame {frame}"))


@dataclass
class CaptureSource:
    """A raw capture as described by its reader (nothing is loaded but calibration and fits)."""

    format: str  # avatarctl.io.detect.FORMATS, or "video"
    root: Path
    cameras: list[Camera]  # as calibrated (distorted), in the capture's order; names are project-safe
    image_frames: dict[str, set[int]]  # camera -> frame numbers that have an image (empty: camera has none)
    images: ImageReader
    fits: BodyFits | None  # None: the capture ships no fits (ingest can estimate them: --fits keypoints)
    fits_where: str = ""  # file or folder the fits came from (for messages)
    masks: MaskReader | None = None  # None: the capture has no mask files
    mask_frames: dict[str, set[int]] | None = None  # camera -> frame numbers that have a mask
    uncalibrated: list[str] = field(default_factory=list)  # image folders with no calibration ("extra cameras")
    backgrounds: dict[str, Path] = field(default_factory=dict)  # camera -> background plate (distorted geometry)
    split: Split | None = None  # the capture's own split, if it ships one
    notes: list[str] = field(default_factory=list)  # what the reader decided, shown to the user
    fps: float = 0.0  # frame rate when the capture states one (videos), else 0
    sequence: str = ""  # the dataset's name of this recording when its folders say it (ActorsHQ "Actor01/Sequence1")
    release_scale: float = 1.0  # scale of these images relative to the dataset's full-resolution release (ActorsHQ
    # 4x folder: 0.25); `--benchmark` scales relative to the full release
    hands_from_mean: bool = False  # SMPL-X fits whose hand poses are offsets from the model's hand mean (smplx's
    # flat_hand_mean=False); ingest adds the model file's mean (projects store full axis-angle hand poses)

    @property
    def camera_names(self) -> list[str]:
        return [c.name for c in self.cameras]

    @property
    def all_frames(self) -> list[int]:
        """Every frame number that has an image in at least one camera, ascending."""
        return sorted(set().union(*self.image_frames.values())) if self.image_frames else []


def first_image_sizes(per_cam: dict[str, dict[int, Path]]) -> dict[str, tuple[int, int]]:
    """{camera: (width, height)} of each camera's first image file ({camera: {frame: file}}; cameras without files
    are left out); an unreadable file is a one-line error naming it."""
    import cv2

    sizes = {}
    for cam, found in per_cam.items():
        if found:
            first = found[min(found)]
            img = cv2.imread(str(first), cv2.IMREAD_UNCHANGED)
            if img is None:
                raise InputError(f"image unreadable or corrupt: camera {cam}", where=str(first),
                                 fix="re-export this image, or leave the frame out with --frames")
            sizes[cam] = (int(img.shape[1]), int(img.shape[0]))
    return sizes


def frame_number(path: Path) -> int | None:
    """Frame number of an image file named by its number (`000012.jpg` -> 12), else None."""
    stem = path.stem
    return int(stem) if stem.isdigit() else None


def scan_numbered(folder: Path, suffixes: tuple[str, ...] = IMAGE_SUFFIXES) -> dict[int, Path]:
    """{frame number: file} for the numbered image files directly inside `folder`."""
    out: dict[int, Path] = {}
    if not folder.is_dir():
        return out
    for p in sorted(folder.iterdir()):
        if p.suffix.lower() in suffixes and p.is_file():
            n = frame_number(p)
            if n is not None:
                out[n] = p
    return out


def check_complete(have: dict[str, set[int]], cams: list[str], frames: list[int], what: str, where: Path) -> None:
    """Every camera in `cams` must have every frame in `frames`; else one line naming the camera and frames."""
    for cam in cams:
        got = have.get(cam, set())
        if not got:
            raise InputError(f"camera {cam} has no {what}", where=str(where),
                             fix=f"add its {what} or leave the camera out with --views")
        missing = [f for f in frames if f not in got]
        if missing:
            raise InputError(f"frame-count mismatch: camera {cam} has {len(got)} {what} but {len(frames)} frames "
                             f"are ingested (no {what} for frames {fmt_list(missing)})", where=str(where),
                             fix=f"add the missing {what}, or select frames with --frames / cameras with --views")


def fmt_list(xs: list, n: int = 5) -> str:
    s = ", ".join(str(x) for x in xs[:n])
    return s + (f", … ({len(xs)} in all)" if len(xs) > n else "")
