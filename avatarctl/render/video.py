"""Frames -> MP4 that plays in a browser: H.264 (libx264), yuv420p, even dimensions, `+faststart`.

Written through imageio-ffmpeg (its bundled ffmpeg binary), atomically: a crash leaves no half-written video.
Frames with odd width/height are padded (bottom/right) with `pad_color`, never rescaled.
"""

from __future__ import annotations

import errno
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

import numpy as np

from avatarctl.atomic import atomic_path

VIDEO_CODEC = "libx264"
VIDEO_PIX_FMT = "yuv420p"


@dataclass(frozen=True)
class VideoInfo:
    """What was written."""

    path: Path
    frames: int
    width: int  # pixels, even
    height: int  # pixels, even
    fps: float
    codec: str = VIDEO_CODEC
    pix_fmt: str = VIDEO_PIX_FMT


def pad_even(img: np.ndarray, pad_color: tuple[int, int, int] = (0, 0, 0)) -> np.ndarray:
    """[H, W, 3] uint8 -> [H', W', 3] with H', W' even (one extra row/column of `pad_color` where needed)."""
    H, W = img.shape[:2]
    if H % 2 == 0 and W % 2 == 0:
        return img
    out = np.empty((H + H % 2, W + W % 2, 3), np.uint8)
    out[...] = np.asarray(pad_color, np.uint8)
    out[:H, :W] = img
    return out


def tile(images: list[np.ndarray], columns: int | None = None,
         pad_color: tuple[int, int, int] = (0, 0, 0)) -> np.ndarray:
    """Lay out [H_i, W_i, 3] uint8 images on a grid (row-major), each cell the size of the largest image."""
    assert images, "tile needs at least one image"
    n = len(images)
    cols = columns or int(math.ceil(math.sqrt(n)))
    rows = int(math.ceil(n / cols))
    h = max(i.shape[0] for i in images)
    w = max(i.shape[1] for i in images)
    out = np.empty((rows * h, cols * w, 3), np.uint8)
    out[...] = np.asarray(pad_color, np.uint8)
    for k, img in enumerate(images):
        r, c = divmod(k, cols)
        out[r * h:r * h + img.shape[0], c * w:c * w + img.shape[1]] = img[..., :3]
    return out


def write_video(frames: Iterable[np.ndarray], dest: str | Path, fps: float,
                pad_color: tuple[int, int, int] = (0, 0, 0), crf: int = 18) -> VideoInfo:
    """Encode [H, W, 3] uint8 RGB frames (all the same size) into an H.264/yuv420p MP4 at `dest`, atomically."""
    import imageio_ffmpeg

    if not fps > 0:
        raise ValueError(f"fps must be > 0, got {fps}")
    dest = Path(dest)
    n = 0
    size: tuple[int, int] | None = None
    with atomic_path(dest, suffix=".mp4") as tmp:
        writer = None
        try:
            for frame in frames:
                f = np.asarray(frame)
                assert f.dtype == np.uint8 and f.ndim == 3 and f.shape[2] == 3, \
                    f"video frames must be [H, W, 3] uint8, got {f.shape} {f.dtype}"
                f = pad_even(f, pad_color)
                if writer is None:
                    size = (f.shape[1], f.shape[0])
                    writer = imageio_ffmpeg.write_frames(
                        str(tmp), size, pix_fmt_in="rgb24", pix_fmt_out=VIDEO_PIX_FMT, fps=fps, codec=VIDEO_CODEC,
                        quality=None, macro_block_size=2, ffmpeg_log_level="error",
                        output_params=["-crf", str(crf), "-preset", "medium", "-movflags", "+faststart"])
                    writer.send(None)  # start the generator
                assert (f.shape[1], f.shape[0]) == size, f"frame {n} is {f.shape[1]}x{f.shape[0]}, video is {size}"
                writer.send(np.ascontiguousarray(f))
                n += 1
            if writer is None:
                raise ValueError("no frames to write")
        finally:
            if writer is not None:
                writer.close()
        _check_written(tmp, n, dest)
    assert size is not None
    return VideoInfo(path=dest, frames=n, width=size[0], height=size[1], fps=float(fps))


def _check_written(path: Path, frames: int, dest: Path) -> None:
    """imageio-ffmpeg does not look at ffmpeg's exit status: when ffmpeg cannot write (disk full, file-size limit)
    the video is cut short and nothing says so. Count the frames ffmpeg can read back (a decode of the file)."""
    import imageio_ffmpeg

    try:
        got, _ = imageio_ffmpeg.count_frames_and_secs(str(path))
    except Exception:  # noqa: BLE001 - an unreadable file is the same failure as a short one
        got = 0
    if got != frames:
        raise OSError(errno.EIO, f"ffmpeg wrote {got} of {frames} video frames (disk full or a file-size limit?)",
                      str(dest))


def probe_video(path: str | Path) -> dict:
    """Codec, pixel format, size, fps and frame count of a video, from ffmpeg's own reading of the file."""
    import imageio_ffmpeg

    gen = imageio_ffmpeg.read_frames(str(path))
    meta = next(gen)
    n = sum(1 for _ in gen)
    return {"codec": str(meta.get("codec", "")), "pix_fmt": str(meta.get("pix_fmt", "")).split("(")[0],
            "size": tuple(meta.get("size", (0, 0))), "fps": float(meta.get("fps", 0.0)), "frames": n}
