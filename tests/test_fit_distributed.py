"""Data-parallel fitting on torch.distributed (gloo, CPU): the occupancy merge, the shard rules, 2 ranks against
1 rank of the same ray shards, resume across N = 2 -> 1, a killed rank and Ctrl-C. Toy body, micro preset, a few
steps; every multi-process run has a timeout."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from fixtures.toy_capture import make_toy_capture

from avatarctl.errors import InputError
from avatarctl.fit.distributed import check_shards, merge_occupancy
from avatarctl.model.occupancy import UNSEEN, update_occupancy

TINY = ("val_every=0", "val_pairs=0", "log_every=1", "checkpoint_every=1", "keep_checkpoints=10")
RANK_TOL = 1e-5  # max |parameter difference| after a few steps, 2 ranks vs 1 (measured: 0, bitwise, on CPU)
WAIT_S = 90  # no multi-process test may take longer than this


# ---- pure rules -------------------------------------------------------------------------------------------------
def test_merged_occupancy_equals_one_update_over_all_observations():
    g = torch.Generator().manual_seed(0)
    before = torch.rand(64, generator=g) * 3
    before[::5] = UNSEEN
    cells = torch.randint(64, (200,), generator=g)
    dens = torch.rand(200, generator=g) * 4
    one = before.clone()
    update_occupancy(one, cells, dens, 0.9)
    halves = []
    for part in (slice(0, 100), slice(100, 200)):
        a = before.clone()
        update_occupancy(a, cells[part], dens[part], 0.9)
        halves.append(a)
    assert torch.equal(merge_occupancy(before, halves), one)
    assert torch.equal(merge_occupancy(before, [before.clone()]), before)


@pytest.mark.parametrize("shards, world, rays, images, needle", [
    (2, 3, 128, 2, "cannot share"),
    (4, 2, 128, 2, "multiples"),
    (8, 1, 128, 8, "pairs"),
])
def test_shard_rules_are_one_line_input_errors(shards, world, rays, images, needle):
    with pytest.raises(InputError, match=needle) as e:
        check_shards(shards, world, rays, images, pairs=6)
    assert "\n" not in e.value.one_line()


# ---- multi-process runs -----------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def toy_project(tmp_path_factory):
    from avatarctl.stages import ingest
    from avatarctl.stages.ingest import IngestConfig

    root = tmp_path_factory.mktemp("dist")
    cap, proj = make_toy_capture(root / "cap"), root / "proj"
    ingest.run(proj, IngestConfig(capture=cap, project=proj))
    return proj


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def _params(path: Path) -> dict[str, torch.Tensor]:
    return torch.load(path, weights_only=True)["model"]


def _max_diff(a: dict, b: dict) -> float:
    assert a.keys() == b.keys()
    return max(float((a[k].double() - b[k].double()).abs().max()) if a[k].numel() else 0.0 for k in a)


def _env() -> dict[str, str]:
    root = str(Path(__file__).resolve().parents[1])
    return {**os.environ, "PYTHONPATH": os.pathsep.join([root, os.environ.get("PYTHONPATH", "")]),
            "OMP_NUM_THREADS": "1", "AVATARCTL_DIST_TIMEOUT": "30"}


def test_two_ranks_match_one_rank_and_resume_on_one(toy_project, tmp_path):
    """Same ray shards (S = 2) -> same rays, noise, loss normalisation and occupancy grids: 2 ranks of R/2 rays equal
    1 rank of R rays; a fit started on 2 ranks continues on 1 as if it had not stopped."""
    from avatarctl.stages import fit
    from avatarctl.stages.fit import FitRequest

    one, two = _copy(toy_project, tmp_path / "one"), _copy(toy_project, tmp_path / "two")
    base = dict(preset="micro", overrides=TINY, device="cpu")
    r1 = fit.run(one, FitRequest(iters=4, shards=2, **base), handle_sigint=False)
    t0 = time.perf_counter()
    r2 = fit.run(two, FitRequest(iters=2, nproc=2, **base))
    assert time.perf_counter() - t0 < WAIT_S
    assert r2.step == 2 and r2.config.rays_per_batch == 128
    ckpt = lambda p, s: p / "fit" / "checkpoints" / f"step_{s:08d}.pt"  # noqa: E731
    assert _max_diff(_params(ckpt(one, 2)), _params(ckpt(two, 2))) <= RANK_TOL
    occ1, occ2 = _params(ckpt(one, 2))["occupancy"], _params(ckpt(two, 2))["occupancy"]
    assert (occ1 >= 0).any() and torch.allclose(occ1, occ2, atol=RANK_TOL)  # the grids were updated, identically
    tau = _params(ckpt(two, 2)).get("pose_refine.tau")  # per-frame corrections (when the preset refines poses)
    assert tau is None or tau.abs().max() > 0  # they moved, and the parameter check above covers them
    r3 = fit.run(two, FitRequest(iters=4, resume=True, device="cpu"), handle_sigint=False)  # N = 2 -> 1
    assert r3.step == 4 and r1.step == 4
    assert _max_diff(_params(ckpt(one, 4)), _params(ckpt(two, 4))) <= RANK_TOL
    assert abs(r1.losses["total"] - r3.losses["total"]) <= 1e-3 * abs(r1.losses["total"])
    from avatarctl.project import Project

    rec = Project.open(two).manifest.stages[-1]
    assert rec.stage == "fit"


def test_gaussian_field_on_two_ranks_matches_one_rank_of_the_same_shards(toy_project, tmp_path):
    """`model.field=gaussians` (whole crops instead of rays): 2 ranks of one image each = 1 rank of both shards,
    the relocation of dead Gaussians (at step 2) and the per-camera colour transforms (model/colour.py) included."""
    from avatarctl.stages import fit
    from avatarctl.stages.fit import FitRequest

    one, two = _copy(toy_project, tmp_path / "one"), _copy(toy_project, tmp_path / "two")
    sets = TINY + ("model.field=gaussians", "model.gaussians.per_node=16", "model.colour.enabled=true")
    base = dict(preset="micro", overrides=sets, model_settings={"gaussians": {"relocate_every": 2}}, device="cpu")
    fit.run(one, FitRequest(iters=3, shards=2, **base), handle_sigint=False)
    t0 = time.perf_counter()
    r2 = fit.run(two, FitRequest(iters=3, nproc=2, **base))
    assert time.perf_counter() - t0 < WAIT_S and r2.step == 3
    ckpt = lambda p: p / "fit" / "checkpoints" / f"step_{3:08d}.pt"  # noqa: E731
    a, b = _params(ckpt(one)), _params(ckpt(two))
    # the Gaussians start isotropic, where a rotation changes nothing: their quaternions' gradients are rounding
    # noise, which Adam scales to steps of about its learning rate, and two ranks sum it in another order
    qa, qb = a.pop("fields.quats"), b.pop("fields.quats")
    assert "fields.means" in a and _max_diff(a, b) <= RANK_TOL
    # (measured: one of 2,048 components 1.3e-4 apart, the rest within 1e-4): within one Adam step, lr_quats 1e-3
    assert torch.allclose(qa, qb, atol=1e-3) and (qa - qb).abs().gt(1e-4).float().mean() < 0.01
    assert b["camera_colour.log_gain"].abs().max() > 0  # the transforms learned, alike on both ranks (above)


def test_resume_on_more_ranks_than_shards_reshards_and_says_so(toy_project, tmp_path):
    """A fit of 1 shard resumed on 2 ranks: new shards (2), their own streams, a note in the log."""
    import json

    from avatarctl.fit.checkpoint import read_checkpoint
    from avatarctl.stages import fit
    from avatarctl.stages.fit import FitRequest

    proj = _copy(toy_project, tmp_path / "p")
    fit.run(proj, FitRequest(preset="micro", iters=2, overrides=TINY, device="cpu"), handle_sigint=False)
    r = fit.run(proj, FitRequest(iters=4, resume=True, nproc=2, device="cpu"))
    assert r.step == 4
    assert read_checkpoint(proj / "fit" / "checkpoints" / "latest.pt")["rng"]["sampler_shards"].shape[0] == 2
    notes = [json.loads(ln) for ln in (proj / "fit" / "log.jsonl").read_text().splitlines() if "note" in ln]
    assert len(notes) == 1 and notes[0]["step"] == 2 and "resharded to 2" in notes[0]["note"]


@pytest.mark.skipif(shutil.which("torchrun") is None and not (Path(sys.executable).parent / "torchrun").is_file(),
                    reason="torchrun not installed")
def test_torchrun_ranks_read_the_environment_and_train_like_one_process(toy_project, tmp_path):
    """The cluster path: torchrun starts the ranks (RANK / WORLD_SIZE / MASTER_* in the environment)."""
    from avatarctl.stages import fit
    from avatarctl.stages.fit import FitRequest

    one, two = _copy(toy_project, tmp_path / "one"), _copy(toy_project, tmp_path / "two")
    fit.run(one, FitRequest(preset="micro", iters=2, shards=2, overrides=TINY, device="cpu"), handle_sigint=False)
    torchrun = shutil.which("torchrun") or str(Path(sys.executable).parent / "torchrun")
    proc = subprocess.run([torchrun, "--standalone", "--nproc_per_node", "2", "-m", "avatarctl", "fit", str(two),
                           "--preset", "micro", "--iters", "2", "--device", "cpu",
                           *sum((["--set", s] for s in TINY), [])], capture_output=True, text=True, env=_env(),
                          timeout=WAIT_S)
    assert proc.returncode == 0, proc.stderr[:4000] + "\n[...]\n" + proc.stderr[-1500:]  # the ranks' lines come first
    assert proc.stdout.count("avatarctl fit") == 1  # rank 0 reports, rank 1 is quiet
    latest = lambda p: p / "fit" / "checkpoints" / "latest.pt"  # noqa: E731
    assert _max_diff(_params(latest(one)), _params(latest(two))) <= RANK_TOL


@pytest.mark.parametrize("rank", [False, True])
def test_a_torchrun_rank_ends_without_the_interpreter_teardown_and_keeps_its_exit_status(rank):
    """Under torchrun (WORLD_SIZE set) `python -m avatarctl` ends through `os._exit` once its output is flushed: no
    teardown of torch / gloo thread pools (where a finished rank occasionally aborted), the command's exit status."""
    code = ("import atexit, sys; atexit.register(lambda: print('teardown ran')); sys.argv = ['avatarctl'] + "
            "sys.argv[1:]; from avatarctl.__main__ import run; run()")
    env = {k: v for k, v in _env().items() if k not in ("WORLD_SIZE", "RANK")}
    env.update({"WORLD_SIZE": "1", "RANK": "0"} if rank else {})
    ok = subprocess.run([sys.executable, "-c", code, "--version"], capture_output=True, text=True, env=env,
                        timeout=WAIT_S)
    assert ok.returncode == 0 and ok.stdout.startswith("avatarctl ")
    assert ("teardown ran" in ok.stdout) is not rank
    bad = subprocess.run([sys.executable, "-c", code, "no-such-command"], capture_output=True, text=True, env=env,
                         timeout=WAIT_S)
    assert bad.returncode == 2 and "No such command" in bad.stderr


def test_bad_rank_options_are_one_line_errors_before_or_from_the_ranks(toy_project, tmp_path):
    """Shard arithmetic is checked before any rank starts; an AvatarError inside the ranks (here: resume without a
    checkpoint) comes back as that one-line error, not a traceback."""
    from avatarctl.errors import ProjectError
    from avatarctl.stages import fit
    from avatarctl.stages.fit import FitRequest

    proj = _copy(toy_project, tmp_path / "p")
    res = subprocess.run([sys.executable, "-m", "avatarctl", "fit", str(proj), "--preset", "micro", "--nproc", "3",
                          "--device", "cpu"], capture_output=True, text=True, env=_env(), timeout=WAIT_S)
    assert res.returncode != 0 and "Traceback" not in res.stderr
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "must be multiples of the 3 ray shards" in lines[0], res.stderr
    assert not (proj / "fit" / "checkpoints").exists() or not any((proj / "fit" / "checkpoints").iterdir())
    with pytest.raises(ProjectError, match="checkpoint not found"):
        fit.run(proj, FitRequest(resume=True, nproc=2, device="cpu"))


def _spawn_cli(args: list[str], **kw) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "avatarctl", *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=_env(), **kw)


def _wait_for(path: Path, proc: subprocess.Popen, seconds: float = WAIT_S) -> None:
    t0 = time.perf_counter()
    while not path.exists():
        assert proc.poll() is None, proc.communicate()
        assert time.perf_counter() - t0 < seconds, f"{path} never appeared"
        time.sleep(0.1)


def _rank_pids(parent: int) -> list[int]:
    """The spawned ranks of `parent` (not its multiprocessing resource tracker), in pid order."""
    pids = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            ppid = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
            cmd = (d / "cmdline").read_bytes()
        except (OSError, IndexError, ValueError):
            continue
        if ppid == parent and b"spawn_main" in cmd:
            pids.append(int(d.name))
    return sorted(pids)


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="needs /proc to find the ranks")
def test_a_killed_rank_is_reported_and_the_checkpoint_survives(toy_project, tmp_path):
    from avatarctl.fit.checkpoint import read_checkpoint

    proj = _copy(toy_project, tmp_path / "p")
    proc = _spawn_cli(["fit", str(proj), "--preset", "micro", "--iters", "100000", "--device", "cpu", "--nproc", "2",
                       *sum((["--set", s] for s in TINY), [])])
    try:
        _wait_for(proj / "fit" / "checkpoints" / "step_00000002.pt", proc)
        ranks = _rank_pids(proc.pid)
        assert len(ranks) == 2
        os.kill(ranks[-1], signal.SIGKILL)
        out, err = proc.communicate(timeout=WAIT_S)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode != 0
    assert "SIGKILL" in err and "rank" in err and "--resume" in err and "Traceback" not in err, err
    assert read_checkpoint(proj / "fit" / "checkpoints" / "latest.pt")["step"] >= 2


def test_ctrl_c_stops_every_rank_after_the_same_step_with_a_checkpoint(toy_project, tmp_path):
    from avatarctl.fit.checkpoint import read_checkpoint

    proj = _copy(toy_project, tmp_path / "p")
    proc = _spawn_cli(["fit", str(proj), "--preset", "micro", "--iters", "100000", "--device", "cpu", "--nproc", "2",
                       *sum((["--set", s] for s in TINY), [])], start_new_session=True)
    try:
        _wait_for(proj / "fit" / "checkpoints" / "step_00000002.pt", proc)
        os.killpg(proc.pid, signal.SIGINT)  # what the terminal does: the whole foreground group
        out, err = proc.communicate(timeout=WAIT_S)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 0, err
    assert "stopped early" in out and "--resume" in out
    ckpt = read_checkpoint(proj / "fit" / "checkpoints" / "latest.pt")
    assert 2 <= ckpt["step"] < 100000 and ckpt["rng"]["sampler_shards"].shape[0] == 2
