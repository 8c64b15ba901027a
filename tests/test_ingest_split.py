"""ingest/split.py: a capture's split.json checked against its cameras, then restricted to the ingested views."""

from __future__ import annotations

import pytest

from avatarctl.errors import InputError
from avatarctl.ingest.split import check_split_views, restrict_split
from avatarctl.io.project_io import Split

CAMS = ["cam00", "cam01", "cam02", "cam03"]


def _split(test_views: list[str], train_views: list[str] | None = None) -> Split:
    return Split(train_frames=[0, 1], test_frames=[2], train_views=train_views or ["cam00", "cam02"],
                 test_views=test_views)


def test_a_view_the_capture_lacks_is_a_one_line_error_naming_it():
    with pytest.raises(InputError) as e:
        check_split_views(_split(["cam01", "zz99"]), CAMS, where="cap/split.json")
    msg = str(e.value)
    assert "test_views names 'zz99', a view the capture lacks" in msg and "cap/split.json" in msg
    assert "cam00, cam01, cam02, cam03" in msg and len(msg.splitlines()) == 1
    with pytest.raises(InputError, match="train_views names 'cam9'"):
        check_split_views(_split(["cam01"], train_views=["cam9"]), CAMS, where="cap/split.json")


def test_a_view_left_out_with_views_is_dropped_quietly():
    split = _split(["cam01", "cam03"])
    check_split_views(split, CAMS, where="cap/split.json")  # every view exists: no error
    kept = restrict_split(split, frames=[0, 1, 2], views=["cam00", "cam01"])  # --views cam00,cam01
    assert kept.test_views == ["cam01"] and kept.train_views == ["cam00"]
