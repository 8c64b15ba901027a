"""Output locks: one writer of an output at a time, freed by the kernel when its holder dies.

The lock of an output path D (a project being ingested, a project's `fit/`, `render/<name>`, `eval/<name>`,
`export/<name>`, `project.json`) is the file `.<D.name>.lock` beside D, held with the operating system's advisory
lock (`fcntl.flock`, exclusive). The kernel drops it when its holder exits or is killed, so a lock never outlives a
process and there is no PID to check. While held, the file records the holder (`Holder`: command, pid, host, since)
for the refusal message; the holder deletes it when done (a waiter that then locks the deleted file notices and
locks the new one), so a project at rest has none.

Who runs with whom is decided by which outputs two commands write (docs/reliability.md, "Concurrency"); the stages
take these locks (`stages.common.writing`), `Project.record` takes the manifest's.

The holder of D's lock owns D's temporaries: taking it tidies what killed writers of D left (`atomic.recover`), and
`sweep(folder)` does the same for every output of a folder whose lock is free at that moment.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import fcntl
import json
import os
import socket
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Iterator

from avatarctl.atomic import recover, temp_owner
from avatarctl.errors import BusyError


@dataclass(frozen=True)
class Holder:
    """Who holds a lock (recorded in the lock file for the message of a command it refuses)."""

    command: str  # e.g. "fit --resume", "render --name orbit"
    pid: int
    host: str
    since: str  # ISO 8601, UTC, seconds

    @classmethod
    def this_process(cls, command: str) -> "Holder":
        since = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
        return cls(command=command, pid=os.getpid(), host=socket.gethostname(), since=since)

    def describe(self) -> str:
        return f"`{self.command}` (pid {self.pid} on {self.host}, since {self.since})"


def lock_file(dest: str | os.PathLike) -> Path:
    """The lock file of the output `dest`: `.<name>.lock` beside it."""
    dest = Path(os.path.abspath(dest))
    return dest.parent / f".{dest.name}.lock"


def _same_file(fd: int, path: Path) -> bool:
    try:
        st = path.stat()
    except FileNotFoundError:
        return False
    own = os.fstat(fd)
    return (own.st_dev, own.st_ino) == (st.st_dev, st.st_ino)


def _read_holder(fd: int) -> Holder | None:
    """The holder a lock file names; None while it is still writing itself in (or for a foreign file)."""
    try:
        return Holder(**json.loads(os.pread(fd, 4096, 0)))
    except (OSError, ValueError, TypeError):
        return None


def _acquire(path: Path, wait: bool) -> int | Holder | None:
    """A descriptor of `path` locked by this process, or (not waiting, the lock taken) whoever holds it."""
    path.parent.mkdir(parents=True, exist_ok=True)
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | (0 if wait else fcntl.LOCK_NB))
        except BlockingIOError:
            holder = _read_holder(fd)
            os.close(fd)
            return holder
        except BaseException:
            os.close(fd)
            raise
        if _same_file(fd, path):
            return fd
        os.close(fd)  # its holder deleted it as we waited for it: lock the file now at the path


def _release(fd: int, path: Path) -> None:
    if _same_file(fd, path):
        with contextlib.suppress(FileNotFoundError):
            path.unlink()
    os.close(fd)  # unlocks


@contextlib.contextmanager
def hold(dest: str | os.PathLike, command: str, *, wait: bool = False) -> Iterator[Holder]:
    """Hold the lock of the output `dest` for the block. Taken: what killed writers of `dest` left beside it is
    tidied (`atomic.recover`). Held by another process: `BusyError` naming it, or with `wait` block until it is
    free. The lock file's folder is created if missing."""
    path = lock_file(dest)
    got = _acquire(path, wait)
    if not isinstance(got, int):
        who = got.describe() if got is not None else "another avatarctl command (starting up)"
        raise BusyError(f"{path.name[1:-len('.lock')]} is being written by {who}", where=str(dest),
                        fix="run again when it has finished, add --wait to queue behind it, or stop it")
    me = Holder.this_process(command)
    try:
        os.ftruncate(got, 0)
        os.pwrite(got, json.dumps(asdict(me)).encode(), 0)
        recover(dest)
        yield me
    finally:
        _release(got, path)


def sweep(folder: str | os.PathLike) -> list[Path]:
    """Tidy, in `folder`, what killed writers left of every output whose lock is free now (`atomic.recover`);
    outputs being written by a live process are left alone. Returns what was deleted."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    removed: list[Path] = []
    for name in sorted({n for n in map(temp_owner, folder.iterdir()) if n is not None}):
        dest = folder / name
        got = _acquire(lock_file(dest), wait=False)
        if isinstance(got, int):
            try:
                removed += recover(dest)
            finally:
                _release(got, lock_file(dest))
    return removed
