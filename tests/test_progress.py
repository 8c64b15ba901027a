"""avatarctl/progress.py: the one progress report, labelled and timed by a stage, renamed by a chain."""

from __future__ import annotations

from avatarctl.progress import ProgressReport, for_stage, relabel


def test_a_stage_labels_and_times_a_librarys_reports():
    seen: list[ProgressReport] = []
    on = for_stage(seen.append, "ingest")
    on(ProgressReport(done=2, total=4, part="frames"))
    relabel(on, "ingest capture-a")(ProgressReport(done=3, total=4, part="detect"))  # the chain's label wins last
    assert [(p.stage, p.done, p.total, p.part) for p in seen] == [("ingest", 2, 4, "frames"),
                                                                   ("ingest", 3, 4, "detect")]
    assert all(p.seconds >= 0 for p in seen) and seen[0].per_second >= 0


def test_relabel_renames_every_report_and_none_stays_none():
    seen: list[ProgressReport] = []
    relabel(seen.append, "render orbit")(ProgressReport(done=1, total=2, stage="render", seconds=0.5))
    assert seen[0].stage == "render orbit" and seen[0].seconds == 0.5 and seen[0].per_second == 2.0
    assert for_stage(None, "fit") is None and relabel(None, "fit") is None
