"""The ingest stage (`avatarctl ingest CAPTURE PROJECT`): a raw capture -> a project directory, through the ingest
library (`avatarctl.ingest.pipeline.run_ingest`); every ingested frame (and, when fits or masks are estimated, every
detected view and fit step) is reported as a `ProgressReport` (`avatarctl.progress`) whose `part` is "frames",
"detect" or "fit"."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

from avatarctl.ingest.config import IngestConfig
from avatarctl.progress import ProgressFn, for_stage
from avatarctl.stages.common import writing

if TYPE_CHECKING:
    from avatarctl.ingest.pipeline import IngestResult

__all__ = ["IngestConfig", "detect", "run"]


def detect(capture: str | Path) -> tuple[str, str]:
    """(format, why) of a capture folder (what `--format auto` picks)."""
    from avatarctl.io.detect import detect_format

    return detect_format(Path(capture))


def run(project_dir: str | Path, cfg: IngestConfig, progress: ProgressFn | None = None, *,
        wait: bool = False) -> "IngestResult":
    """Build the project `project_dir` from `cfg.capture` (see `avatarctl.ingest.pipeline`). Holds the lock of the
    path `project_dir` (another ingest into it is refused with `BusyError`, or waited for with `wait`)."""
    from avatarctl.ingest.pipeline import run_ingest

    on_frame = for_stage(progress, "ingest")
    with writing(Path(project_dir), "ingest", wait):
        return run_ingest(replace(cfg, project=Path(project_dir)), progress=on_frame)
