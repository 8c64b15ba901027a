"""The synth stage (`avatarctl synth OUT`): a synthetic ground-truth capture in EasyMocap layout, through the synth
library (`avatarctl.synth.synthesize`); simulated and rendered frames are reported as `StageProgress` (`part`:
"simulate" | "render")."""

from __future__ import annotations

import time
from pathlib import Path
from typing import TYPE_CHECKING

from avatarctl.stages.common import StageProgress, ProgressFn
from avatarctl.synth.config import SynthConfig

if TYPE_CHECKING:
    from avatarctl.synth import SynthResult

__all__ = ["SynthConfig", "run"]


def run(out: str | Path, cfg: SynthConfig, progress: ProgressFn | None = None) -> "SynthResult":
    """Write the capture into `out` (which must not exist or be empty)."""
    from avatarctl.synth import synthesize

    t0 = time.perf_counter()

    def on_frame(part: str, done: int, total: int) -> None:
        if progress is not None:
            progress(StageProgress(stage="synth", done=done, total=total, seconds=time.perf_counter() - t0, part=part))

    return synthesize(Path(out), cfg, on_frame)
