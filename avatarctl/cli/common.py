"""Shared CLI helpers: the rich console and the mapping of `AvatarError` to exit codes."""

from __future__ import annotations

import contextlib
from typing import Iterator

import typer
from rich.console import Console

from avatarctl.errors import AvatarError

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
