"""One phone video (or a folder of its frames) as a capture: ONE static camera, no calibration, masks or fits.

Camera: pinhole, principal point at the image centre, no distortion (phones correct their lens in the video),
at the world origin looking down +z: R = I, T = 0. So the **world frame is the camera's** (OpenCV: +x right, +y
down, +z forward into the scene, metres); "up" is −y for a phone held level and upright. The body fit places the
subject in front of the camera (`avatarctl.ingest.estimate.estimate_monocular`).

Focal length, first that applies (the summary names the source):

1. ``--focal-px F``: F pixels (of the video's own frames, before ``--resize``);
2. ``--fov-deg A``: the **diagonal** field of view, as phone spec sheets state it: F = (diagonal / 2) / tan(A / 2);
3. the video's metadata: a 35 mm-equivalent focal length (`FOCAL_35MM_KEYS`, e.g. the
   ``com.apple.quicktime.camera.focal_length.35mm_equivalent`` tag iPhones write): F = f35 x diagonal / 43.27 mm
   (43.27 mm: the diagonal of a 36 x 24 mm frame);
4. the default, `DEFAULT_FOCAL_35MM` = 26 mm equivalent (79.5 deg diagonal): the main (wide) camera of most phones
   since 2018 is 24-28 mm equivalent. A wrong focal length scales the depth of the fitted body; it does not move
   it in the image.

Frames: a video file (any container ffmpeg reads; frame number = 0-based index) or a folder of images (sorted by
name; frame number = position in that order). Frames that are all the same are fine; ingest checks the length.
"""

from __future__ import annotations

import math
import re
import subprocess
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from avatarctl.errors import InputError
from avatarctl.io.capture import IMAGE_SUFFIXES, CaptureSource, FileImages, make_camera
from avatarctl.io.video import VIDEO_SUFFIXES

CAMERA = "cam00"  # the one camera's name in the project
DEFAULT_FOCAL_35MM = 26.0  # mm, 35 mm-equivalent focal length of a phone's main camera (module docstring)
FULL_FRAME_DIAGONAL_MM = 43.27  # diagonal of a 36 x 24 mm frame
FOCAL_35MM_KEYS = ("com.apple.quicktime.camera.focal_length.35mm_equivalent", "focal_length_35mm",
                   "focallengthin35mmformat", "focal_length.35mm_equivalent")  # metadata keys (lower case)
CALIBRATION_FILES = ("intri.yml", "annots.npy", "calibration.json", "camera.pkl", "cameras.bin", "cameras.txt")


def is_monocular_source(path: Path) -> bool:
    """A video file, or a folder that holds image files directly and no calibration of any known format."""
    path = Path(path)
    if path.is_file():
        return path.suffix.lower() in VIDEO_SUFFIXES
    if not path.is_dir() or any((path / n).exists() for n in CALIBRATION_FILES + ("sparse", "images", "videos")):
        return False
    return any(p.suffix.lower() in IMAGE_SUFFIXES for p in path.iterdir() if p.is_file())


@dataclass(frozen=True)
class Intrinsics:
    focal_px: float  # at the video's own resolution
    source: str  # where it came from, for the summary


def focal_from_35mm(f35: float, width: int, height: int) -> float:
    """Pixels of a 35 mm-equivalent focal length `f35` (mm) for a `width` x `height` image."""
    return f35 * math.hypot(width, height) / FULL_FRAME_DIAGONAL_MM


def diagonal_fov_deg(focal_px: float, width: int, height: int) -> float:
    return math.degrees(2 * math.atan(math.hypot(width, height) / 2 / focal_px))


def resolve_intrinsics(width: int, height: int, focal_px: float | None, fov_deg: float | None,
                       metadata_f35: float | None) -> Intrinsics:
    """The focal length by the rule of the module docstring."""
    if focal_px is not None:
        return Intrinsics(float(focal_px), f"--focal-px {focal_px:g}")
    if fov_deg is not None:
        f = math.hypot(width, height) / 2 / math.tan(math.radians(fov_deg) / 2)
        return Intrinsics(f, f"--fov-deg {fov_deg:g} (diagonal)")
    if metadata_f35 is not None:
        f = focal_from_35mm(metadata_f35, width, height)
        return Intrinsics(f, f"video metadata: {metadata_f35:g} mm 35 mm-equivalent "
                             f"({diagonal_fov_deg(f, width, height):.1f} deg diagonal)")
    f = focal_from_35mm(DEFAULT_FOCAL_35MM, width, height)
    return Intrinsics(f, f"default: a phone's main camera, {DEFAULT_FOCAL_35MM:g} mm 35 mm-equivalent "
                         f"({diagonal_fov_deg(f, width, height):.1f} deg diagonal); pass --focal-px or --fov-deg")


def video_focal_35mm(path: Path) -> float | None:
    """The 35 mm-equivalent focal length (mm) a video's container metadata carries, else None (read with the
    ffmpeg that `imageio_ffmpeg` bundles: ``ffmpeg -i FILE -f ffmetadata -``)."""
    import imageio_ffmpeg

    try:
        out = subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-v", "error", "-i", str(path), "-f", "ffmetadata",
                              "-"], capture_output=True, text=True, timeout=60, errors="replace").stdout
    except (OSError, subprocess.SubprocessError):
        return None
    for line in out.splitlines():
        key, _, value = line.partition("=")
        if key.strip().lower() in FOCAL_35MM_KEYS:
            m = re.match(r"\s*([0-9]+(?:\.[0-9]+)?)", value)
            if m and 5.0 <= float(m.group(1)) <= 300.0:
                return float(m.group(1))
    return None


def scan_frames(folder: Path) -> dict[int, Path]:
    """{frame number: image} of a folder of frames: files sorted by name, numbered 0, 1, ..."""
    files = sorted(p for p in Path(folder).iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)
    return dict(enumerate(files))


def read_monocular(path: Path, focal_px: float | None = None, fov_deg: float | None = None) -> CaptureSource:
    """The `CaptureSource` of one video file or folder of frames (see the module docstring)."""
    import cv2

    path = Path(path)
    if path.is_file():
        from avatarctl.io.video import VideoImages, video_info

        info = video_info(path)
        if info.frames == 0:
            raise InputError("the video has no frames", where=str(path), fix="check the file (ffmpeg -i FILE)")
        width, height, fps = info.width, info.height, info.fps
        frames = set(range(info.frames))
        images = VideoImages(paths={CAMERA: path}, sizes={CAMERA: (width, height)})
        f35 = video_focal_35mm(path)
    else:
        per = scan_frames(path)
        if not per:
            raise InputError("the folder holds no image files", where=str(path),
                             fix="pass a video file or a folder of frames (.jpg / .png)")
        first = cv2.imread(str(per[0]), cv2.IMREAD_UNCHANGED)
        if first is None:
            raise InputError("image unreadable or corrupt", where=str(per[0]), fix="re-export the frames")
        height, width = first.shape[:2]
        frames, images, fps, f35 = set(per), FileImages({(CAMERA, f): p for f, p in per.items()}), 0.0, None
    intr = resolve_intrinsics(width, height, focal_px, fov_deg, f35)
    K = np.array([[intr.focal_px, 0.0, (width - 1) / 2], [0.0, intr.focal_px, (height - 1) / 2], [0.0, 0.0, 1.0]])
    cam = make_camera(path, name=CAMERA, K=K, R=np.eye(3), T=np.zeros(3), width=width, height=height,
                      dist=np.zeros(5))
    return CaptureSource(format="video", root=path, cameras=[cam], image_frames={CAMERA: frames}, images=images,
                         fits=None, fps=fps, notes=[f"intrinsics: {intr.source}"])
