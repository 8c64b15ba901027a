"""The one progress report of avatarctl: `ProgressReport`, sent to a `ProgressFn`.

A library reports what it knows (`done` of `total` units of its `part`: rays, frames, iterations); the stage that
called it adds its own label and the time since its units started (`for_stage`); a chain of stages renames the
label of each stage it runs (`relabel`: "render orbit", "fit skirt-full-s0"). The CLI turns reports into a bar.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from typing import Any, Callable


@dataclass(frozen=True)
class ProgressReport:
    """`done` of `total` units of `part` of `stage`."""

    done: int  # units done: rays, frames, steps, iterations or images
    total: int | None  # None while unknown
    part: str = ""  # a sub-step ("detect" | "fit" | "frames" for ingest, "simulate" | "render" for synth), else ""
    stage: str = ""  # synth | ingest | fit | render | eval | export (a chain: "render orbit", ...); "" in a library
    seconds: float = 0.0  # since the stage started its units (0 in a library's own report)
    detail: Any = None  # the stage's own typed record: fit `StepReport`, eval `ImageScore`, else None

    @property
    def per_second(self) -> float:
        return self.done / self.seconds if self.seconds > 0 else 0.0


ProgressFn = Callable[[ProgressReport], None]


def for_stage(progress: ProgressFn | None, stage: str) -> ProgressFn | None:
    """`progress` fed with a library's reports labelled `stage` and timed from this call."""
    if progress is None:
        return None
    t0 = time.perf_counter()

    def f(p: ProgressReport) -> None:
        progress(replace(p, stage=stage, seconds=time.perf_counter() - t0))
    return f


def relabel(progress: ProgressFn | None, stage: str) -> ProgressFn | None:
    """`progress` with `stage` as the label of every report (a chain's "render orbit", "fit skirt-full-s0", ...)."""
    if progress is None:
        return None

    def f(p: ProgressReport) -> None:
        progress(replace(p, stage=stage))
    return f
