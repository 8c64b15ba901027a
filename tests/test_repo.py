"""Repository contract: top-level layout, README commands, CI script."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _readme_commands() -> list[str]:
    text = (ROOT / "README.md").read_text()
    return re.findall(r"```bash\n(.+?)\n```", text)


def test_readme_first_screen_has_demo_and_test_commands():
    cmds = _readme_commands()
    assert len(cmds) >= 2, cmds
    demo, tests = cmds[0], cmds[1]
    assert "torch==2.13.0" in demo and "avatarctl demo" in demo
    assert "torch==2.13.0" in tests and "pytest" in tests
    # the first screen: both commands within the first 25 lines
    head = "\n".join((ROOT / "README.md").read_text().splitlines()[:25])
    assert demo in head and tests in head


def test_ci_runs_the_readme_test_command():
    tests_cmd = _readme_commands()[1]
    ci = (ROOT / ".ci" / "run").read_text()
    assert tests_cmd in ci.splitlines(), "'.ci/run' must run the README's test command verbatim"
    assert "set -euo pipefail" in ci


def test_top_level_layout():
    names = {p.name for p in ROOT.iterdir() if not p.name.startswith(".")} - {"build", "dist", "out"}
    names = {n for n in names if not n.endswith(".egg-info")}
    assert {"avatarctl", "tests", "docs", "pyproject.toml", "README.md"} <= names
    assert names <= {"avatarctl", "benchmarks", "tests", "docs", "pyproject.toml", "README.md"}, names


def test_benchmarks_and_test_toys_live_outside_the_core_model():
    model = {p.name for p in (ROOT / "avatarctl" / "model").glob("*.py")}
    assert not model & {"bench.py", "toy.py"}, model
    assert (ROOT / "benchmarks" / "bench.py").is_file()


def test_no_licensed_model_files_in_repo():
    bad = [p for p in ROOT.rglob("*") if p.suffix.lower() in {".pkl"} and ".venv" not in p.parts]
    assert not bad, f"model/data pickles must not be committed: {bad}"


def test_docs_hold_no_scripts():
    """Nothing under docs/ that can break without a test noticing: an experiment's scripts leave the tree (its README
    names the commit that holds them) or become a tested `benchmarks/` module."""
    scripts = [str(p.relative_to(ROOT)) for p in (ROOT / "docs").rglob("*") if p.suffix in {".py", ".sh"}]
    assert not scripts, f"move these into benchmarks/ with a test, or out of the tree: {scripts}"
