"""The one rule for comma-separated lists on the command line and in `--set` values (`--views 00,03`,
`--knockout delta-n,embedding`, `--background 0.2,0.2,0.2`, `--set model.snapshot_at_s=120,300`, ...).

Spaces around an item are dropped, and so are empty items (a trailing comma, `a,,b`); `None`, `""` or only commas
and spaces give the empty tuple. Whether an empty list or a given count is allowed is the caller's rule.
"""

from __future__ import annotations

from typing import Callable, TypeVar

T = TypeVar("T")


def split_list(spec: str | None, conv: Callable[[str], T] = str) -> tuple[T, ...]:  # type: ignore[assignment]
    """'a, b,,c,' -> ('a', 'b', 'c'); with `conv` each item converted ('1, 2.5' with float -> (1.0, 2.5)).

    A `ValueError` of `conv` propagates: the caller turns it into its own one-line error (it knows the option)."""
    if not spec:
        return ()
    return tuple(conv(item) for item in (x.strip() for x in spec.split(",")) if item)
