"""Error types shared by every stage.

Stages raise `AvatarError` with a one-line, actionable message (what went wrong, where, how to fix it).
Only the CLI turns these into exit codes; library code never calls `sys.exit`.
"""

from __future__ import annotations


class AvatarError(Exception):
    """A user-facing error: one line saying what, where, and how to fix it."""

    exit_code: int = 2

    def __init__(self, what: str, where: str | None = None, fix: str | None = None):
        self.what = what
        self.where = where
        self.fix = fix
        super().__init__(self.one_line())

    def one_line(self) -> str:
        parts = [self.what]
        if self.where:
            parts.append(f"({self.where})")
        msg = " ".join(parts)
        if self.fix:
            msg += f" -> {self.fix}"
        return msg


class InputError(AvatarError):
    """Bad user input: capture files, options, motion files."""


class ProjectError(AvatarError):
    """A project directory that is missing, from an unknown schema, or lacks a stage output."""


class BusyError(AvatarError):
    """Another command is writing what this one would write (`avatarctl.lock`). Exit 75 (EX_TEMPFAIL): the same
    command can succeed later."""

    exit_code = 75


class NotBuiltError(AvatarError):
    """A stage that is not implemented yet. Exits non-zero; never produces fake output."""

    exit_code = 3
