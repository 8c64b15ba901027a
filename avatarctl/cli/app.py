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
def _root(ctx: typer.Context,
          version: bool = typer.Option(False, "--version", callback=_version, is_eager=True,
                                       help="Print the version and exit."),
          debug: bool = typer.Option(False, "--debug", help="Show Python tracebacks instead of one-line errors "
                                                            "(same as AVATARCTL_DEBUG=1).")) -> None:
    """Animatable clothed human avatars from calibrated RGB video."""
    import os

    from avatarctl.cli.common import DEBUG_ENV, debug_enabled
    from avatarctl.stages.common import quiet_kernels

    quiet_kernels(not (debug or debug_enabled()))  # Warp's lines only when debugging
    if debug:
        previous = os.environ.get(DEBUG_ENV)
        os.environ[DEBUG_ENV] = "1"  # read by cli.common.user_errors in the command that follows

        def restore() -> None:  # only for this invocation (matters when the app is called in-process)
            if previous is None:
                os.environ.pop(DEBUG_ENV, None)
            else:
                os.environ[DEBUG_ENV] = previous

        ctx.call_on_close(restore)


def _register() -> None:
    from avatarctl.cli import demo, evaluate, export, fit, info, ingest, motion, render, reproduce, synth, view

    for mod in (synth, ingest, fit, render, evaluate, motion, export, view, demo, reproduce, info):
        mod.register(app)


_register()


def main() -> None:
    from avatarctl.allocator import tune

    tune()  # glibc: keep large tensors' pages in the heap (see avatarctl/allocator.py)
    app()


if __name__ == "__main__":
    main()
