"""benchmarks/ingest_memory.py at toy scale: the generated ActorsHQ-layout capture ingests whole, memory is sampled
after every frame, and the folder is removed unless kept."""

from __future__ import annotations

import json


def test_ingest_memory_generates_ingests_and_measures(tmp_path):
    from benchmarks.ingest_memory import main

    from avatarctl.io.project_io import load_project_capture
    from avatarctl.project import Project

    out = tmp_path / "mem.json"
    res = main(["--cams", "3", "--frames", "10", "--size", "48", "--keep", str(tmp_path / "run"), "--out", str(out)])
    assert (res.cams, res.frames, res.images) == (3, 10, 30) and res.capture_mb > 0
    assert res.ingest_seconds > 0 and res.images_per_second > 0
    assert set(res.rss_mb) == {"10%", "50%", "100%"} and res.peak_rss_mb >= max(res.rss_mb.values()) > 0
    assert res.rss_growth_mb == round(res.rss_mb["100%"] - res.rss_mb["10%"], 1)
    pc = load_project_capture(Project.open(tmp_path / "run" / "project"))
    assert pc.frames == list(range(10)) and sorted(pc.cameras) == ["Cam001", "Cam002", "Cam003"]
    assert pc.image("Cam002", 9).shape == (48, 48, 3) and pc.mask("Cam002", 9).any()
    assert json.loads(out.read_text())["images"] == 30


def test_ingest_memory_removes_its_temporary_capture(tmp_path, monkeypatch):
    import tempfile

    from benchmarks.ingest_memory import main

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    res = main(["--cams", "2", "--frames", "2", "--size", "32", "--no-contact-sheet"])
    assert res.images == 4 and list(tmp_path.iterdir()) == []
