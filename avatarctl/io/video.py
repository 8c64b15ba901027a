"""Per-camera video files as a capture's images: ``videos/<cam>.mp4`` (any container ffmpeg reads).

Frame number = index of the decoded frame (0-based). Decoding goes through `imageio_ffmpeg` (a core
dependency; it bundles an ffmpeg binary). Frames are decoded sequentially: `VideoImages` keeps one open decoder
per camera and only reopens it when a frame before the last one read is asked for, so reading the frames of a
camera in ascending order (what ingest does) decodes each frame once.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import numpy as np

from avatarctl.errors import InputError

VIDEO_SUFFIXES = (".mp4", ".mov", ".avi", ".mkv", ".webm")


def scan_videos(folder: Path) -> dict[str, Path]:
    """{camera name (file stem): video file} directly inside `folder`."""
    if not folder.is_dir():
        return {}
    return {p.stem: p for p in sorted(folder.iterdir()) if p.is_file() and p.suffix.lower() in VIDEO_SUFFIXES}


@dataclass(frozen=True)
class VideoInfo:
    frames: int  # number of decodable frames
    width: int
    height: int
    fps: float


def video_info(path: Path) -> VideoInfo:
    """Frame count (exact: counted by decoding), size and frame rate of a video; one-line error if unreadable."""
    import imageio_ffmpeg

    try:
        gen = imageio_ffmpeg.read_frames(str(path))
        meta = next(gen)
        gen.close()
        n, _ = imageio_ffmpeg.count_frames_and_secs(str(path))
    except (OSError, RuntimeError, StopIteration, ValueError) as e:
        raise InputError(f"video unreadable ({type(e).__name__})", where=str(path),
                         fix="re-encode it (e.g. ffmpeg -i IN -c:v libx264 -pix_fmt yuv420p OUT.mp4) or extract "
                             "its frames to images/<cam>/%06d.jpg") from None
    w, h = (int(v) for v in meta["size"])
    return VideoInfo(frames=int(n), width=w, height=h, fps=float(meta.get("fps") or 0.0))


@dataclass
class VideoImages:
    """`ImageReader` over one video per camera (see the module docstring)."""

    paths: dict[str, Path]  # camera -> video file
    sizes: dict[str, tuple[int, int]]  # camera -> (width, height)
    _open: dict[str, tuple[Iterator, int]] = field(default_factory=dict, repr=False)  # camera -> (decoder, next)

    def read(self, cam: str, frame: int) -> np.ndarray:
        """RGB uint8 [H, W, 3] of frame `frame` (0-based) of camera `cam`."""
        import imageio_ffmpeg

        if cam not in self.paths:
            raise InputError(f"no video for camera {cam}", fix="check --views")
        gen, nxt = self._open.get(cam, (None, 0))
        if gen is None or frame < nxt:
            if gen is not None:
                gen.close()
            gen = imageio_ffmpeg.read_frames(str(self.paths[cam]), pix_fmt="rgb24")
            next(gen)  # metadata
            nxt = 0
        w, h = self.sizes[cam]
        try:
            while True:
                buf = next(gen)
                nxt += 1
                if nxt - 1 == frame:
                    break
        except StopIteration:
            self._open.pop(cam, None)
            raise InputError(f"video of camera {cam} has no frame {frame}", where=str(self.paths[cam]),
                             fix="select frames inside the video with --frames") from None
        self._open[cam] = (gen, nxt)
        return np.frombuffer(buf, dtype=np.uint8).reshape(h, w, 3).copy()

    def where(self, cam: str, frame: int) -> str:
        return f"{self.paths.get(cam, 'videos/' + cam)} frame {frame}"

    def close(self) -> None:
        for gen, _ in self._open.values():
            gen.close()
        self._open.clear()
