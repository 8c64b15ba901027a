"""Checks of the generated ingest captures (`tests/fixtures/captures.py`)."""

from __future__ import annotations

import pytest
from fixtures.captures import make_easymocap_capture


@pytest.mark.anny
def test_fixture_capture_is_easymocap_with_a_visible_body(tmp_path):
    from avatarctl.io.detect import detect_format

    cap = make_easymocap_capture(tmp_path / "cap", frames=[0], n_cams=2)
    assert detect_format(cap.root)[0] == "easymocap"
    import cv2

    m = cv2.imread(str(cap.root / "masks" / "00" / "000000.png"), cv2.IMREAD_GRAYSCALE)
    frac = (m > 0).mean()
    assert 0.02 < frac < 0.5, frac  # the body is in view and not filling the frame
