"""Shared CLI helpers: the rich console, the progress bar every long stage shows, and the mapping of errors to exit
codes: `AvatarError` -> its one line and its code (2, 3); an operating-system refusal to write or read (disk full,
read-only file system, permission, quota) -> one line and 74; anything else is a bug -> one line and 70. With
`avatarctl --debug ...` or `AVATARCTL_DEBUG=1` every error is re-raised with its Python traceback."""

from __future__ import annotations

import contextlib
import errno
import os
from typing import TYPE_CHECKING, Iterator

import typer
from rich.console import Console

from avatarctl.errors import AvatarError

if TYPE_CHECKING:
    from rich.progress import Progress

console = Console(stderr=False, highlight=False)
err_console = Console(stderr=True, highlight=False)


WAIT_HELP = ("If another command is writing the same output (a fit of this project, a render / eval / export of "
             "the same name, an ingest into the same PROJECT), wait for it to finish instead of stopping at once "
             "(exit 75).")
DEBUG_ENV = "AVATARCTL_DEBUG"  # "1": tracebacks instead of one-line errors (what `avatarctl --debug` sets)
EXIT_OS = 74  # EX_IOERR: the system refused a read or write (disk full, read-only, permission)
EXIT_BUG = 70  # EX_SOFTWARE: an unexpected exception, i.e. a bug in avatarctl
# errno values that are the environment's fault, not avatarctl's: reported as one line with a fix
_OS_FIX = {errno.ENOSPC: "free disk space (or write the project elsewhere) and run the command again",
           errno.EDQUOT: "free space within your quota and run the command again",
           errno.EROFS: "write the project to a writable file system",
           errno.EACCES: "check the permissions of that path",
           errno.EPERM: "check the permissions of that path",
           errno.EFBIG: "a file-size limit (ulimit -f, or the file system's) stopped the write: raise it",
           errno.EIO: "check the disk (I/O error) and run the command again",
           errno.EMFILE: "raise the open-file limit (ulimit -n)",
           errno.ENAMETOOLONG: "use a shorter path"}


def debug_enabled() -> bool:
    return os.environ.get(DEBUG_ENV, "") not in ("", "0")


def _say(text: str) -> None:
    from rich.markup import escape

    err_console.print(f"[bold red]error:[/] {escape(text)}", soft_wrap=True)


def one_line_error(e: Exception) -> tuple[str, int]:
    """(message, exit code) of the one line the CLI prints for `e`."""
    if isinstance(e, AvatarError):
        return e.one_line(), e.exit_code
    if isinstance(e, OSError) and e.errno in _OS_FIX:
        where = e.filename2 or e.filename
        what = f"{e.strerror or os.strerror(e.errno)}" + (f" ({where})" if where else "")
        return f"the system refused a file operation: {what} -> {_OS_FIX[e.errno]}", EXIT_OS
    detail = " ".join(str(e).split())[:200]
    return (f"internal error: {type(e).__name__}: {detail} -> this is a bug in avatarctl; run again with "
            f"`avatarctl --debug ...` (or {DEBUG_ENV}=1) for the traceback and report it"), EXIT_BUG


@contextlib.contextmanager
def user_errors() -> Iterator[None]:
    """Turn any exception into one red line and a non-zero exit (see the module docstring); re-raise it unchanged
    when debugging is on."""
    try:
        yield
    except KeyboardInterrupt:
        if debug_enabled():
            raise
        err_console.print("[yellow]interrupted[/]")
        raise typer.Exit(code=130) from None
    except (typer.Exit, typer.Abort):
        raise
    except Exception as e:  # noqa: BLE001 - the one place errors become exit codes
        if debug_enabled():
            raise
        message, code = one_line_error(e)
        _say(message)
        raise typer.Exit(code=code) from None


def progress_bar(label: str, fields: tuple[str, ...] = (), *, out: Console | None = None,
                 bar_width: int | None = None) -> "Progress":
    """The one progress bar of the CLI: `label`, bar, done/total, the task's `fields` (text set with
    `bar.update(task, <field>=...)`), elapsed time and ETA."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, \
        TimeRemainingColumn

    columns = [TextColumn(f"[bold]{label}[/]"), BarColumn(bar_width=bar_width), MofNCompleteColumn()]
    columns += [TextColumn(f"{{task.fields[{f}]}}") for f in fields]
    columns += [TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn()]
    return Progress(*columns, console=out or console, transient=False)
