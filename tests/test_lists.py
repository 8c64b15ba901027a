"""avatarctl/lists.py: the one comma-list rule, and the options that use it."""

from __future__ import annotations

import pytest

from avatarctl.lists import split_list


@pytest.mark.parametrize("spec, items", [
    ("a,b,c", ("a", "b", "c")),
    (" a , b ,c ", ("a", "b", "c")),  # spaces around items dropped
    ("a,,b,", ("a", "b")),  # empty items dropped
    ("", ()), (None, ()), (" , ,", ()),
    ("cam 01,cam02", ("cam 01", "cam02")),  # spaces inside an item kept
])
def test_split_list_items(spec, items):
    assert split_list(spec) == items


def test_split_list_converts_and_lets_the_caller_name_the_error():
    assert split_list("1, 2.5,", float) == (1.0, 2.5)
    assert split_list("3,1", int) == (3, 1)
    with pytest.raises(ValueError):
        split_list("1,x", float)


def test_the_options_share_the_rule():
    """Spaces and a trailing comma mean the same in every option that takes a list."""
    from avatarctl.fit.config import apply_overrides, parse_ablations, preset
    from avatarctl.frames import parse_frame_spec
    from avatarctl.stages.common import parse_knockout
    from avatarctl.stages.render import parse_background

    assert parse_knockout(" delta-n, embedding,") == ("delta-n", "embedding")
    assert parse_ablations("no-delta-n, ") == ("no-delta-n",)
    assert parse_background(" 0.5, 0.25,1 ", (0.0, 0.0, 0.0)) == ((0.5, 0.25, 1.0), False)
    assert parse_frame_spec("4, 1,") == parse_frame_spec("1,4")
    assert apply_overrides(preset("micro"), ["snapshot_at_s=120, 300,"]).snapshot_at_s == (120.0, 300.0)
