"""benchmarks/mask_accuracy.py on the toy project: a copy whose masks are 1 px too thin in every view and hold a
far blob in one is scored against the original."""

from __future__ import annotations

import json
import math
import shutil

import numpy as np


def test_mask_accuracy_sorts_the_errors_by_ring_and_prices_them(toy_fitted_project, tmp_path):
    import cv2

    from avatarctl.io.project_io import load_project_capture
    from avatarctl.project import Project
    from benchmarks.mask_accuracy import main, measure

    est = tmp_path / "est"
    shutil.copytree(toy_fitted_project / "ingest", est / "ingest")
    shutil.copy(toy_fitted_project / "project.json", est / "project.json")
    same = measure(est, toy_fitted_project)
    assert same.iou == 1.0 and same.false_positive_total == 0 and same.false_negative_total == 0
    assert same.masked_frame_psnr == math.inf

    cap = load_project_capture(Project.open(est))
    cams, frames = sorted(cap.cameras), cap.frames
    cross = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))
    fg = lost = blob = 0
    for c in cams:
        for f in frames:
            t = cap.mask(c, f)
            thin = cv2.erode(t.astype(np.uint8), cross) > 0  # the first ring inside the outline lost
            if c == cams[0] and f == frames[0]:
                assert not t[:3, :3].any()
                thin[:3, :3] = True  # a blob in the corner, far from the person
                blob = 9
            cv2.imwrite(str(est / "ingest" / "masks" / c / f"{f:06d}.png"), thin.astype(np.uint8) * 255)
            fg, lost = fg + int(t.sum()), lost + int((t & ~thin).sum())
    r = measure(est, toy_fitted_project)
    assert r.images == len(cams) * len(frames) and 0.5 < r.iou < 1.0
    assert math.isclose(r.false_negative["1"], lost / fg) and r.false_negative["2"] == r.false_negative["3+"] == 0
    assert r.false_positive["1"] == r.false_positive["2"] == 0 and math.isclose(r.false_positive["3+"], blob / fg)
    assert 5.0 < r.masked_frame_psnr < 60.0

    held_out = measure(est, toy_fitted_project, split="test")
    s = cap.split
    expected = len([v for v in s.test_views if v not in s.train_views]) * len(s.train_frames) \
        + len(s.test_views) * len(s.test_frames)
    assert held_out.images == expected
    out = tmp_path / "m.json"
    main([str(est), str(toy_fitted_project), "--json", str(out)])
    assert math.isclose(json.loads(out.read_text())["iou"], r.iou)
