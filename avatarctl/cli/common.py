"""Shared CLI helpers: the rich console, the progress bar every long stage shows, and the mapping of `AvatarError`
to exit codes."""

from __future__ import annotations

import contextlib
from typing import TYPE_CHECKING, Iterator

import typer
from rich.console import Console

from avatarctl.errors import AvatarError

if TYPE_CHECKING:
    from rich.progress import Progress

console = Console(stderr=False, highlight=False)
err_console = Console(stderr=True, highlight=False)


@contextlib.contextmanager
def user_errors() -> Iterator[None]:
    """Turn `AvatarError` into a one-line red message and a non-zero exit. Anything else is a bug: re-raised."""
    try:
        yield
    except AvatarError as e:
        from rich.markup import escape

        err_console.print(f"[bold red]error:[/] {escape(e.one_line())}", soft_wrap=True)
        raise typer.Exit(code=e.exit_code) from None
    except KeyboardInterrupt:
        err_console.print("[yellow]interrupted[/]")
        raise typer.Exit(code=130) from None


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
