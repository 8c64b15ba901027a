"""Issue 32: two commands on one project, and a power cut — nothing lost, nothing mixed.

- locks (`avatarctl.lock`): a second writer of an output is refused at once with one line naming the holder (real
  processes here; every command × output pair is in tests/test_faults.py), the first is unharmed; a reader
  (render) runs during a fit and both records survive in project.json; a lock whose holder was killed frees
  itself; `--wait` queues; torchrun ranks > 0 take none; concurrent manifest records are all kept;
- durable writes (`avatarctl.atomic`): the fsync / rename / folder-fsync order, observed through the calls (no
  root, no power cut needed), for a file, a folder and a checkpoint; every rename of the package goes through
  `durable_replace`;
- stale temporaries of killed writers are tidied by the next writer, never those of a live one.
"""

from __future__ import annotations

import ast
import contextlib
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from fixtures.toy_capture import make_toy_project
from typer.testing import CliRunner

from avatarctl import atomic
from avatarctl.cli.app import app
from avatarctl.errors import BusyError
from avatarctl.lock import hold, lock_file, sweep

REPO = Path(__file__).resolve().parents[1]
PKG = REPO / "avatarctl"
HOLD = ("import sys\nfrom avatarctl.lock import hold\nwith hold(sys.argv[1], sys.argv[2]):\n"
        "    print('held', flush=True)\n    sys.stdin.read()\n")


def _env() -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1", "AVATARCTL_DEBUG": "0"}


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "avatarctl.cli.app", *args]


@contextlib.contextmanager
def _held_elsewhere(dest: Path, command: str):
    """Another process holding `dest`'s lock for the block (released when its stdin closes)."""
    proc = subprocess.Popen([sys.executable, "-c", HOLD, str(dest), command], env=_env(), stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE)
    assert proc.stdout.readline().strip() == b"held"
    try:
        yield proc
    finally:
        if proc.poll() is None:
            proc.stdin.close()
        proc.wait(timeout=30)


@pytest.fixture(scope="module")
def toy(tmp_path_factory) -> dict[str, Path]:
    from avatarctl.stages import fit
    from avatarctl.stages.fit import FitRequest

    root = tmp_path_factory.mktemp("lock")
    cap, proj = make_toy_project(root)
    fit.run(proj, FitRequest(preset="micro", iters=2, overrides=("val_every=0", "checkpoint_every=2", "log_every=1"),
                             device="cpu"), handle_sigint=False)
    return {"capture": cap, "project": proj}


# ---- two writers, a reader, a killed writer (real processes) -------------------------------------------------------
def test_a_second_fit_is_refused_a_render_runs_during_the_fit_and_a_killed_fit_frees_its_lock(toy, tmp_path):
    from avatarctl.fit.checkpoint import read_checkpoint
    from avatarctl.project import Project

    proj = tmp_path / "proj"
    shutil.copytree(toy["project"], proj)
    shutil.copytree(toy["capture"], tmp_path / "cap")
    stale = [proj / "render" / ".default.tmp-deadbeef", proj / "fit" / ".config.json.tmp-x1.json"]
    stale[0].mkdir(parents=True)
    stale[1].write_text("{")
    log = proj / "fit" / "log.jsonl"
    lines = log.read_bytes().count(b"\n")
    first = subprocess.Popen(_cli("fit", str(proj), "--resume", "--iters", "100000", "--device", "cpu"), env=_env(),
                             stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        t0 = time.perf_counter()
        while log.read_bytes().count(b"\n") < lines + 3:  # the first fit is training (its lock held)
            assert first.poll() is None and time.perf_counter() - t0 < 120, first.stderr.read()
            time.sleep(0.05)
        assert not stale[1].exists(), "the fit tidies what a killed fit left in fit/"
        second = CliRunner().invoke(app, ["fit", str(proj), "--fresh", "--preset", "micro", "--device", "cpu"])
        err = second.stderr.strip()  # this process is the second writer
        assert second.exit_code == 75 and len(err.splitlines()) == 1, err
        assert f"fit is being written by `fit --resume` (pid {first.pid} on " in err and " -> " in err, err
        res = CliRunner().invoke(app, ["render", str(proj), "--device", "cpu", "--frames", "0", "--views", "cam00"])
        assert res.exit_code == 0, res.output  # a reader during a fit: it reads one whole checkpoint
        assert not stale[0].exists(), "the render tidies what a killed render of that name left"
        assert first.poll() is None, "the first fit was harmed"
    finally:
        first.send_signal(signal.SIGKILL)
        first.wait()
    step = read_checkpoint(proj / "fit" / "checkpoints" / "latest.pt")["step"]
    res = CliRunner().invoke(app, ["fit", str(proj), "--resume", "--iters", str(step + 1), "--device", "cpu"])
    assert res.exit_code == 0, res.output  # the killed fit's lock freed itself
    stages = [r.stage for r in Project.open(proj).manifest.stages]
    assert stages == ["ingest", "fit", "render", "fit"], stages  # the render's record kept by the fit's
    assert read_checkpoint(proj / "fit" / "checkpoints" / "latest.pt")["step"] == step + 1
    assert not list(proj.rglob(".*.lock")) and not list(proj.rglob(".*.tmp-*"))


def test_a_lock_whose_holder_was_killed_is_free_and_names_the_holder_while_held(tmp_path):
    dest = tmp_path / "P" / "fit"
    with _held_elsewhere(dest, "fit --resume") as other:
        with pytest.raises(BusyError) as e:
            with hold(dest, "fit"):
                pass
        line = e.value.one_line()
        assert f"fit is being written by `fit --resume` (pid {other.pid} on " in line and ", since 20" in line
        assert line.endswith("-> run again when it has finished, add --wait to queue behind it, or stop it")
        other.kill()
        other.wait()
        assert lock_file(dest).exists()  # left by the killed holder, with its name in it ...
        with hold(dest, "fit") as me:  # ... but free
            assert me.pid == os.getpid()
    assert not lock_file(dest).exists()


def test_wait_queues_behind_the_holder(tmp_path):
    dest = tmp_path / "render" / "default"
    order = []
    taken = threading.Event()

    def first():
        with hold(dest, "render --name default"):
            taken.set()
            time.sleep(0.3)
            order.append("first done")

    t = threading.Thread(target=first)
    t.start()
    taken.wait(10)
    with hold(dest, "render --name default", wait=True):  # another open file description: a second holder
        order.append("second in")
    t.join()
    assert order == ["first done", "second in"]


def test_only_rank_0_of_a_torchrun_launch_takes_the_lock(tmp_path, monkeypatch):
    from avatarctl.stages.common import writing

    dest = tmp_path / "fit"
    with hold(dest, "fit"):
        monkeypatch.setenv("WORLD_SIZE", "2")
        monkeypatch.setenv("RANK", "1")
        with writing(dest, "fit", wait=False) as held:
            assert held is False
        monkeypatch.setenv("RANK", "0")
        with pytest.raises(BusyError):
            with writing(dest, "fit", wait=False):
                pass


def test_records_written_together_are_all_kept(toy, tmp_path):
    proj = tmp_path / "proj"
    shutil.copytree(toy["project"], proj)
    code = ("import sys\nfrom avatarctl.project import Project\np = Project.open(sys.argv[1])\n"
            "for i in range(10):\n    p.record('eval', {'writer': sys.argv[2], 'i': i}, [], '')\n")
    procs = [subprocess.Popen([sys.executable, "-c", code, str(proj), str(w)], env=_env()) for w in range(4)]
    assert [p.wait(timeout=120) for p in procs] == [0] * 4
    from avatarctl.project import Project

    recs = [(r.config["writer"], r.config["i"]) for r in Project.open(proj).manifest.stages if r.stage == "eval"]
    assert sorted(recs) == [(str(w), i) for w in range(4) for i in range(10)]


# ---- durable writes ------------------------------------------------------------------------------------------------
@pytest.fixture
def calls(monkeypatch) -> list[tuple[str, str]]:
    """('fsync', path) / ('replace', dest) / ('unlink', path) in the order they happen."""
    if not Path("/proc/self/fd").is_dir():
        pytest.skip("needs /proc to name the file an fsync is for")
    seen: list[tuple[str, str]] = []
    real_fsync, real_replace, real_unlink = os.fsync, os.replace, os.unlink

    def fsync(fd):
        seen.append(("fsync", os.readlink(f"/proc/self/fd/{fd}")))
        real_fsync(fd)

    def replace(src, dst):
        seen.append(("replace", os.fspath(dst)))
        real_replace(src, dst)

    def unlink(path, *a, **k):
        seen.append(("unlink", os.fspath(path)))
        real_unlink(path, *a, **k)

    monkeypatch.setattr(os, "fsync", fsync)
    monkeypatch.setattr(os, "replace", replace)
    monkeypatch.setattr(os, "unlink", unlink)
    return seen


def test_a_file_is_fsynced_renamed_and_its_folder_fsynced(tmp_path, calls):
    dest = (tmp_path / "new" / "a.json").resolve()
    atomic.write_json(dest, {"a": 1})
    assert calls[0] == ("fsync", str(tmp_path.resolve()))  # the new folder's entry, in its parent
    kind, tmp = calls[1]
    assert kind == "fsync" and Path(tmp).name.startswith(".a.json.tmp-")
    assert calls[2] == ("replace", str(dest))
    assert calls[3] == ("fsync", str(dest.parent)) and len(calls) == 4


def test_a_folder_is_fsynced_whole_before_its_rename(tmp_path, calls):
    dest = (tmp_path / "render" / "x").resolve()
    dest.parent.mkdir()
    with atomic.atomic_dir(dest) as tmp:
        atomic.write_bytes(tmp / "frames" / "000000.png", b"png")  # published with the folder: no fsync of its own
        atomic.write_text(tmp / "config.json", "{}")
        assert not [c for c in calls if c[0] == "fsync"]
    names = [Path(p).name for kind, p in calls if kind == "fsync"]
    last = [i for i, c in enumerate(calls) if c[0] == "replace"][-1]
    assert calls[last] == ("replace", str(dest))
    before = {Path(p).name for kind, p in calls[:last] if kind == "fsync"}
    assert {"000000.png", "config.json", "frames"} <= before and tmp.name in before
    assert calls[last + 1:] == [("fsync", str(dest.parent))] and len(names) == len(before) + 1


def test_a_checkpoint_is_durable_before_the_last_good_one_goes(toy, tmp_path, calls):
    from avatarctl.fit.checkpoint import save_checkpoint
    from avatarctl.project import Project, ProjectPaths

    proj = Project.open(toy["project"])
    proj.paths = ProjectPaths(tmp_path)  # a throwaway folder: save_checkpoint uses only the checkpoint paths
    save_checkpoint(proj, {"step": 1}, keep=1)
    calls.clear()
    save_checkpoint(proj, {"step": 2}, keep=1)
    folder = str(proj.paths.checkpoints.resolve())
    seq = [(k, "FOLDER" if p == folder else Path(p).name.split(".tmp-")[0] + (".tmp" if ".tmp-" in p else ""))
           for k, p in calls]
    assert seq == [("fsync", ".step_00000002.pt.tmp"), ("replace", "step_00000002.pt"), ("fsync", "FOLDER"),
                   ("unlink", ".latest.pt.tmp"),  # the temporary's name, to hard-link the step file as
                   ("fsync", ".latest.pt.tmp"), ("replace", "latest.pt"), ("fsync", "FOLDER"),
                   ("unlink", "step_00000001.pt")], seq  # the last good one goes once the new one is durable


def test_every_rename_in_the_package_is_the_durable_one():
    """os.replace / os.rename / Path.rename / Path.replace / shutil.move only inside `atomic.durable_replace`."""
    found = []
    for path in sorted(PKG.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)):
                continue
            f = node.func
            owner = f.value.id if isinstance(f.value, ast.Name) else None
            module_call = owner in ("os", "shutil") and f.attr in ("replace", "rename", "renames", "move")
            path_call = f.attr in ("rename", "replace") and len(node.args) == 1 and not node.keywords
            if module_call or path_call:
                found.append(f"{path.relative_to(REPO)}:{node.lineno}")
    text = (PKG / "atomic.py").read_text().splitlines()
    allowed = [f"avatarctl/atomic.py:{i + 1}" for i, line in enumerate(text) if "os.replace(src, dest)" in line]
    assert found == allowed and len(allowed) == 1, found


# ---- stale temporaries ----------------------------------------------------------------------------------------------
def test_sweep_tidies_the_temporaries_of_killed_writers_only(tmp_path):
    folder = tmp_path / "render"
    (folder / "d").mkdir(parents=True)
    for p in (".a.tmp-abcdefgh", ".c.old-77", ".d.old-78"):
        (folder / p).mkdir()
        (folder / p / "frame.png").write_bytes(b"x")
    (folder / ".e.json.tmp-q1w2e3r4.json").write_text("{")
    with hold(folder / "b", "render --name b"):  # a live writer of b: its temporary stays
        (folder / ".b.tmp-12345678").mkdir()
        removed = sweep(folder)
    assert sorted(p.name for p in removed) == [".a.tmp-abcdefgh", ".d.old-78", ".e.json.tmp-q1w2e3r4.json"]
    assert (folder / ".b.tmp-12345678").is_dir()
    assert (folder / "c" / "frame.png").is_file()  # moved aside, never replaced: put back
    assert sorted(p.name for p in folder.iterdir()) == [".b.tmp-12345678", "c", "d"]


def test_an_ingest_tidies_what_a_killed_ingest_into_the_same_project_left(toy, tmp_path):
    stale = tmp_path / ".proj.tmp-abcdefgh"
    (stale / "ingest").mkdir(parents=True)
    other = tmp_path / ".other.tmp-abcdefgh"
    other.mkdir()
    res = CliRunner().invoke(app, ["ingest", str(toy["capture"]), str(tmp_path / "proj"), "--no-contact-sheet"])
    assert res.exit_code == 0, res.output
    assert not stale.exists() and other.exists()  # only its own name's: the folder is the user's
    assert sorted(p.name for p in tmp_path.iterdir()) == [".other.tmp-abcdefgh", "proj"]
