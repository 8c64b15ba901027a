"""Atomic file writes: write to a temporary file in the destination folder, then rename.

A reader never sees a half-written file; a crash leaves at most a stray `*.tmp-*` file, never a truncated output.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any, Iterator


@contextlib.contextmanager
def atomic_path(dest: str | os.PathLike, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path beside `dest`; on success rename it onto `dest`, on error delete it.

    `suffix` defaults to `dest`'s own suffix so that libraries which pick a format by extension
    (imageio, cv2.imwrite, numpy.savez) still work.
    """
    dest = Path(dest)
    dest.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{dest.name}.tmp-", suffix=suffix if suffix is not None else dest.suffix,
                               dir=dest.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        os.replace(tmp_path, dest)
    except BaseException as e:
        with contextlib.suppress(FileNotFoundError):
            tmp_path.unlink()
        if isinstance(e, OSError) and e.filename is None and e.errno is not None:  # a failed write names no file
            raise OSError(e.errno, e.strerror, str(dest)) from e
        raise


def write_bytes(dest: str | os.PathLike, data: bytes) -> Path:
    with atomic_path(dest) as tmp:
        tmp.write_bytes(data)
    return Path(dest)


def write_image(dest: str | os.PathLike, img: Any, params: list[int] | None = None) -> Path:
    """Write `img` (uint8 BGR / BGRA / gray, OpenCV channel order) as the format of `dest`'s suffix, atomically.

    The file is encoded in memory and written by Python, not by `cv2.imwrite`: cv2 reports a refused write (disk
    full, read-only) as a bare False, Python as an `OSError` with its errno, which the CLI explains in one line."""
    import cv2

    ok, buf = cv2.imencode(Path(dest).suffix, img, params or [])
    if not ok:
        raise ValueError(f"OpenCV cannot encode a {img.shape} {img.dtype} image as {Path(dest).suffix}")
    return write_bytes(dest, buf.tobytes())


def write_text(dest: str | os.PathLike, text: str) -> Path:
    return write_bytes(dest, text.encode("utf-8"))


def write_json(dest: str | os.PathLike, obj: Any, indent: int = 2) -> Path:
    return write_text(dest, json.dumps(obj, indent=indent, sort_keys=False, default=_json_default) + "\n")


def _json_default(o: Any) -> Any:
    # numpy scalars / arrays and paths, without importing numpy at module import time
    if hasattr(o, "tolist"):
        return o.tolist()
    if isinstance(o, os.PathLike):
        return os.fspath(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def remove_stale_temps(folder: str | os.PathLike) -> list[Path]:
    """Delete the temporary files / folders `atomic_path` and `atomic_dir` leave in `folder` when the process is
    killed before the rename (`.<name>.tmp-*`). Only for a folder that a single process writes (a project's
    checkpoints while it is being fitted): another writer's in-flight temporary would be deleted too."""
    removed = []
    for p in Path(folder).glob(".*.tmp-*"):
        if p.is_dir():
            shutil.rmtree(p, ignore_errors=True)
        else:
            with contextlib.suppress(FileNotFoundError):
                p.unlink()
        removed.append(p)
    return removed


@contextlib.contextmanager
def atomic_dir(dest: str | os.PathLike) -> Iterator[Path]:
    """Build a whole directory in a temporary sibling and rename it onto `dest` at the end.

    If `dest` exists it is replaced only after the new one is complete.
    """
    dest = Path(dest)
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{dest.name}.tmp-", dir=dest.parent))
    try:
        yield tmp
        if dest.exists():
            old = dest.with_name(f".{dest.name}.old-{os.getpid()}")
            os.replace(dest, old)
            os.replace(tmp, dest)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, dest)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
