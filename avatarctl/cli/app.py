"""`avatarctl`: the Typer app. Each command lives in its own module and imports its stage lazily."""

from __future__ import annotations

import typer

from avatarctl import __version__

app = typer.Typer(
    name="avatarctl",
    help="Animatable clothed human avatars from calibrated RGB video (Structured Local Radiance Fields, CVPR 2022).",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    context_settings={"help_option_names": ["-h", "--help"]},
)


def _version(value: bool) -> None:
    if value:
        typer.echo(f"avatarctl {__version__}")
        raise typer.Exit()


@app.callback()
def _root(version: bool = typer.Option(False, "--version", callback=_version, is_eager=True,
                                       help="Print the version and exit.")) -> None:
    """Animatable clothed human avatars from calibrated RGB video."""


def _register() -> None:
    from avatarctl.cli import demo, evaluate, export, fit, info, ingest, motion, render, synth, view

    for mod in (synth, ingest, fit, render, evaluate, motion, export, view, demo, info):
        mod.register(app)


_register()


def main() -> None:
    from avatarctl.allocator import tune

    tune()  # glibc: keep large tensors' pages in the heap (see avatarctl/allocator.py)
    app()


if __name__ == "__main__":
    main()
