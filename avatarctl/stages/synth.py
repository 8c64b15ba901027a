"""The synth stage (`avatarctl synth OUT`): a synthetic ground-truth capture in EasyMocap layout, through the synth
library (`avatarctl.synth.synthesize`); simulated and rendered frames are reported as a `ProgressReport`
(`avatarctl.progress`; `part`: "simulate" | "render")."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from avatarctl.progress import ProgressFn, for_stage
from avatarctl.synth.config import SynthConfig

if TYPE_CHECKING:
    from avatarctl.synth import SynthResult

__all__ = ["SynthConfig", "run"]


def run(out: str | Path, cfg: SynthConfig, progress: ProgressFn | None = None) -> "SynthResult":
    """Write the capture into `out` (which must not exist or be empty)."""
    from avatarctl.synth import synthesize

    return synthesize(Path(out), cfg, for_stage(progress, "synth"))
