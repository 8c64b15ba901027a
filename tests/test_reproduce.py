"""`avatarctl reproduce` (issue 14): the verdict rules, the report files, option checks, and a micro run end to end
(every table row present; a second invocation reuses every finished unit)."""

from __future__ import annotations

import csv
import io
import json

import pytest
from typer.testing import CliRunner

from avatarctl.errors import InputError


def test_measurement_and_verdicts():
    from avatarctl.evaluate.reproduction import Measurement, difference, verdict

    m = Measurement((20.0, 21.0))
    assert (m.n, m.mean, m.spread) == (2, 20.5, 0.5) and m.text() == "20.50 ± 0.50 dB"
    d = difference(Measurement((22.0, 21.8)), Measurement((20.0, 20.4)))
    assert d.values == pytest.approx((2.0, 1.4))
    assert verdict(d, +1) == "agrees"
    assert verdict(Measurement((-2.0, -1.4)), +1) == "disagrees"
    assert verdict(Measurement((0.6, -0.2)), +1) == "inconclusive"  # seeds disagree
    assert verdict(Measurement((0.05, 0.06)), +1) == "inconclusive"  # under MIN_EFFECT_DB
    assert verdict(Measurement((0.9, 1.0, -0.3)), +1) == "inconclusive"  # one of three seeds disagrees
    assert verdict(Measurement((0.5,)), +1) == "inconclusive"  # one seed, under 1 dB
    assert verdict(Measurement((1.5,)), +1) == "agrees"
    assert verdict(Measurement((1.5, 1.6)), 0) == "no paper number"
    with pytest.raises(ValueError, match="pair"):
        difference(Measurement((1.0,)), Measurement((1.0, 2.0)))


def test_report_lists_every_row_and_the_disagreements():
    from avatarctl.evaluate.reproduction import PAPER, Measurement, ReportRow, report_csv, report_markdown

    rows = [ReportRow("Tab. 1", "skirt", "full - baseline", "eval novel_pose / bbox, PSNR", PAPER["tab1_diff"],
                      Measurement((-0.4, -0.6)), budget="5 steps", verdict="disagrees"),
            ReportRow("supp. Sec. C.2", "bench", "speed-up", "bench", PAPER["sparse_speed"], None, note="--no-bench"),
            ReportRow("Fig. 6", "mono", "full - baseline", "eval novel_view", PAPER["mono"], Measurement((-2.0, -1.0)),
                      verdict="no paper number")]
    md = report_markdown(rows, "T", "P")
    assert "| Tab. 1 | skirt | full - baseline |" in md and "-0.50 ± 0.10 dB" in md and "+3.91 / +1.70 dB" in md
    assert "not run: --no-bench" in md
    assert md.split("## Where our result disagrees")[1].split("##")[0].count("Tab. 1, skirt, full - baseline") == 1
    assert "Fig. 6 (qualitative only (PeopleSnapshot)), mono, full - baseline: ours -1.50 ± 0.50 dB" in \
        md.split("## No paper number, but the full model scores below")[1]
    parsed = list(csv.DictReader(io.StringIO(report_csv(rows))))
    assert [r["verdict"] for r in parsed] == ["disagrees", "", "no paper number"]
    assert parsed[0]["ours_values"] == "-0.4000;-0.6000" and parsed[0]["seeds"] == "2" and parsed[1]["seeds"] == "0"


def test_options_are_checked(tmp_path):
    from avatarctl.stages import reproduce
    from avatarctl.stages.reproduce import ReproduceConfig

    with pytest.raises(InputError, match="no budget"):
        ReproduceConfig(budget_steps=None, minutes=None)
    with pytest.raises(InputError, match="unknown scale"):
        ReproduceConfig(scale="huge")
    with pytest.raises(InputError, match="--seeds"):
        ReproduceConfig(seeds=0)
    assert ReproduceConfig(budget_steps=None, minutes=14.0, seeds=2).fit_seconds == pytest.approx(60.0)
    (tmp_path / "busy").mkdir()
    (tmp_path / "busy" / "mine.txt").write_text("x")
    with pytest.raises(InputError, match="not empty"):
        reproduce.run(tmp_path / "busy", ReproduceConfig(scale="micro"))
    (tmp_path / "old").mkdir()
    (tmp_path / "old" / "reproduce.json").write_text(json.dumps(ReproduceConfig(budget_steps=7).to_json()))
    with pytest.raises(InputError, match="other settings"):
        reproduce.run(tmp_path / "old", ReproduceConfig(budget_steps=8))
    (tmp_path / "old" / "reproduce.json").write_text("{not json")
    with pytest.raises(InputError, match="unreadable reproduce.json"):
        reproduce.run(tmp_path / "old", ReproduceConfig(budget_steps=7))
    res = CliRunner().invoke(__import__("avatarctl.cli.app", fromlist=["app"]).app,
                             ["reproduce", str(tmp_path / "x"), "--seeds", "0"])
    assert res.exit_code != 0 and "--seeds" in res.output


@pytest.mark.slow
@pytest.mark.anny
def test_micro_reproduction_writes_every_table_row_and_resumes(tmp_path):
    from avatarctl.cli.app import app

    out = tmp_path / "rep"
    args = ["reproduce", str(out), "--scale", "micro", "--budget-steps", "2", "--seeds", "2", "--no-bench",
            "--device", "cpu"]
    first = CliRunner().invoke(app, args)
    assert first.exit_code == 0, first.output
    rows = list(csv.DictReader(io.StringIO((out / "report.csv").read_text())))
    tables = [r["paper"] for r in rows]
    for table, n in (("Tab. 1", 3), ("Tab. 2", 6), ("Fig. 6", 6), ("supp. Tab. B", 5), ("supp. Tab. C", 3),
                     ("supp. Sec. C.2", 2)):
        assert tables.count(table) == n, table
    measured = [r for r in rows if r["paper"] != "supp. Sec. C.2"]
    assert all(r["seeds"] == "2" and len(r["ours_values"].split(";")) == 2 for r in measured)
    assert all(r["budget"] == "micro preset, 2 steps per fit" for r in measured)
    assert {r["verdict"] for r in measured if " - " in r["quantity"]} <= {"agrees", "disagrees", "inconclusive",
                                                                          "no paper number"}
    md = (out / "report.md").read_text()
    for r in rows:
        if r["sheet"]:
            assert (out / r["sheet"]).is_file() and f"]({r['sheet']})" in md
    assert "Where our result disagrees" in md and "2 fit seeds" in md
    again = CliRunner().invoke(app, args)  # everything finished: every unit is reused, the report rewritten
    assert again.exit_code == 0, again.output
    units = [line for line in again.output.splitlines() if line.startswith("[") and " bench " not in line]
    assert len(units) == 3 + 14 * 2 + 2 * 14 and all(": reused" in line for line in units), again.output
    assert list(csv.DictReader(io.StringIO((out / "report.csv").read_text()))) == rows
