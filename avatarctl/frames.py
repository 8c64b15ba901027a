"""Frame specs: the one rule for `--frames` (ingest, render, eval).

A spec names capture frame NUMBERS (not positions):
- None / "all": every available frame;
- "train" / "test": the project's split (only where a split is given);
- "a:b" or "a:b:s": the frame numbers n with a <= n < b stepping by s from a (either bound may be empty: a defaults
  to the first available frame, b to past the last);
- "3,7,9": exactly those frames (each must exist).
"""

from __future__ import annotations

from dataclasses import dataclass

from avatarctl.errors import InputError
from avatarctl.lists import split_list

PARSE_FIX = "use all | train | test | a:b[:step] | a comma list of frame numbers"


@dataclass(frozen=True)
class FrameSpec:
    """A parsed `--frames` value (syntax only; membership is checked by `select_frames`)."""

    kind: str  # "all" | "train" | "test" | "range" | "list"
    start: int | None = None  # range: first frame number (None = the first available)
    stop: int | None = None  # range: exclusive end (None = past the last available)
    step: int = 1  # range
    frames: tuple[int, ...] = ()  # list


def parse_frame_spec(spec: str | None, what: str = "--frames") -> FrameSpec:
    """The syntax of a frame spec (see the module docstring); a one-line `InputError` when it cannot be read."""
    s = "" if spec is None else spec.strip()
    if s in ("", "all"):
        return FrameSpec("all")
    if s in ("train", "test"):
        return FrameSpec(s)
    try:
        if ":" in s:
            parts = s.split(":")
            if len(parts) > 3:
                raise ValueError
            start = int(parts[0]) if parts[0] else None
            stop = int(parts[1]) if len(parts) > 1 and parts[1] else None
            step = int(parts[2]) if len(parts) > 2 and parts[2] else 1
            if step <= 0:
                raise ValueError
            return FrameSpec("range", start=start, stop=stop, step=step)
        frames = tuple(sorted(set(split_list(s, int))))
        if not frames:
            raise ValueError
        return FrameSpec("list", frames=frames)
    except ValueError:
        raise InputError(f"cannot parse {what} {spec!r}", where=what, fix=PARSE_FIX) from None


def select_frames(spec: str | None, available: list[int], train: list[int] | None = None,
                  test: list[int] | None = None, what: str = "--frames") -> list[int]:
    """Frame numbers chosen by `spec` among `available` (sorted, unique); `train` / `test`: the project's split."""
    avail = sorted(set(int(f) for f in available))
    parsed = parse_frame_spec(spec, what)
    if parsed.kind == "all":
        return avail
    if parsed.kind in ("train", "test"):
        chosen = train if parsed.kind == "train" else test
        if chosen is None:
            raise InputError(f"{what} {parsed.kind!r} only applies to the project's own frames", where=what,
                             fix="use a range a:b[:step] or a list of frame numbers")
        out = sorted(set(int(f) for f in chosen) & set(avail))
        if not out:
            raise InputError(f"the project has no {parsed.kind} frames", where=what,
                             fix="pick frames with a:b or a list")
        return out
    if parsed.kind == "list":
        missing = [f for f in parsed.frames if f not in set(avail)]
        if missing:
            raise InputError(f"frame(s) {missing[:5]} not available", where=what,
                             fix=f"choose among frames {_ranges(avail)}")
        return list(parsed.frames)
    a = parsed.start if parsed.start is not None else (avail[0] if avail else 0)
    b = parsed.stop if parsed.stop is not None else (avail[-1] + 1 if avail else 0)
    wanted = set(range(a, b, parsed.step))
    out = [f for f in avail if f in wanted]
    if not out:
        raise InputError(f"{what} {spec!r} selects no frame", where=what, fix=f"available frames: {_ranges(avail)}")
    return out


def _ranges(frames: list[int]) -> str:
    if not frames:
        return "none"
    return f"{frames[0]}..{frames[-1]} ({len(frames)} frames)"
