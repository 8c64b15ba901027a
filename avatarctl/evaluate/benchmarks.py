"""Named benchmark protocols: the published evaluation setups of the field's loose-clothing datasets.

A `BenchmarkProtocol` names everything that makes a figure comparable with a paper's: which cameras train and which
are held out, which frames, the image scale, the background the avatar is rendered and the ground truth composited
over, and which pixels are scored (`avatarctl.evaluate.protocols`). `avatarctl ingest --benchmark NAME` applies the
capture side (split, frames, scale); `avatarctl eval` reads the name back from the project and scores under it.

One block per dataset below; `BENCHMARKS` collects them. Camera names are the project-safe names the dataset's
reader (`avatarctl/io/<format>.py`) gives its cameras; frame specs use the `avatarctl.frames` syntax on the
capture's frame NUMBERS.
"""

from __future__ import annotations

from dataclasses import dataclass

from avatarctl.errors import InputError


@dataclass(frozen=True)
class BenchmarkProtocol:
    """One dataset's published protocol, selectable by `name`."""

    name: str  # e.g. "actorshq-physavatar"; lower case, unique
    dataset: str  # the ingest format it applies to ("actorshq" | "dna_rendering" | "4d_dress")
    test_views: tuple[str, ...]  # held-out cameras (project-safe names)
    train_views: tuple[str, ...] | None  # None: every camera not in test_views
    train_frames: str  # `avatarctl.frames` spec on capture frame numbers
    test_frames: str  # idem; the same as train_frames for a novel-view-only protocol
    scale: float  # image scale after undistortion (1.0 = as released)
    background: tuple[float, float, float]  # rgb in [0, 1]: render background and ground-truth compositing colour
    pixels: str  # "full" | "bbox": the pixels scored (`avatarctl.evaluate.protocols.PROTOCOLS`)
    split: str  # the eval split the published figure is over: "novel_view" | "novel_pose"
    comparable_with: tuple[str, ...]  # published figures this protocol is set beside, each "method (venue): figure"
    traps: tuple[str, ...] = ()  # what changes the figure (background, mask compositing, test-pose optimisation)


# --- ActorsHQ (HumanRF) -------------------------------------------------------------------------------------------
_ACTORSHQ: tuple[BenchmarkProtocol, ...] = ()

# --- DNA-Rendering ------------------------------------------------------------------------------------------------
_DNA_RENDERING: tuple[BenchmarkProtocol, ...] = ()

# --- 4D-DRESS -----------------------------------------------------------------------------------------------------
_FOUR_D_DRESS: tuple[BenchmarkProtocol, ...] = ()

BENCHMARKS: dict[str, BenchmarkProtocol] = {p.name: p for p in (*_ACTORSHQ, *_DNA_RENDERING, *_FOUR_D_DRESS)}


def benchmark(name: str) -> BenchmarkProtocol:
    """The protocol called `name`; a one-line InputError listing the known names otherwise."""
    try:
        return BENCHMARKS[name]
    except KeyError:
        known = ", ".join(sorted(BENCHMARKS)) or "none yet"
        raise InputError(f"unknown benchmark protocol {name!r}", where="--benchmark",
                         fix=f"use one of: {known}") from None
