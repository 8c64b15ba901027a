"""`avatarctl synth`: not built yet (see the issue tracker)."""

from __future__ import annotations

import typer


def register(app: typer.Typer) -> None:
    @app.command("synth", help="Make a synthetic ground-truth capture (anny body + simulated dress) in EasyMocap layout.", context_settings={"allow_extra_args": True, "ignore_unknown_options": True})
    def _cmd(ctx: typer.Context) -> None:
        from avatarctl.cli.common import user_errors
        from avatarctl.errors import NotBuiltError

        with user_errors():
            raise NotBuiltError("`avatarctl synth` is not built yet", fix="see the open issues; no output was written")
