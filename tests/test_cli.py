"""CLI shell: commands listed, no heavy imports at start-up, unbuilt stages fail loudly."""

from __future__ import annotations

import subprocess
import sys

from typer.testing import CliRunner

from avatarctl.cli.app import app

COMMANDS = ("synth", "ingest", "fit", "render", "eval", "motion", "demo", "info")


def test_help_lists_every_command_with_one_line_help():
    res = CliRunner().invoke(app, ["--help"])
    assert res.exit_code == 0, res.output
    for cmd in COMMANDS:
        assert f" {cmd} " in res.output, f"{cmd} missing from --help:\n{res.output}"


def test_startup_does_not_import_torch_or_cv2():
    code = ("import sys; import avatarctl.cli.app as a; "
            "bad=[m for m in ('torch','cv2','anny','warp','skimage') if m in sys.modules]; print(bad); "
            "sys.exit(1 if bad else 0)")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert res.returncode == 0, f"heavy modules imported at start-up: {res.stdout} {res.stderr}"


def test_each_command_has_help():
    for cmd in COMMANDS:
        res = CliRunner().invoke(app, [cmd, "--help"])
        assert res.exit_code == 0, f"{cmd}: {res.output}"


def test_info_on_missing_project_is_one_line_error(tmp_path):
    res = CliRunner().invoke(app, ["info", str(tmp_path / "nope")])
    assert res.exit_code == 2
    out = res.output.strip()
    assert "not an avatarctl project" in out and "avatarctl ingest" in out
    assert len(out.splitlines()) == 1, out


def test_version():
    res = CliRunner().invoke(app, ["--version"])
    assert res.exit_code == 0 and res.output.startswith("avatarctl ")


def test_allocator_tuning_applies_on_glibc_and_can_be_switched_off(monkeypatch):
    import platform

    from avatarctl import allocator

    monkeypatch.setenv("AVATARCTL_MALLOC_TUNING", "0")
    assert allocator.tune() is False  # switched off: nothing applied
    monkeypatch.setenv("AVATARCTL_MALLOC_TUNING", "1")
    if platform.system() == "Linux" and platform.libc_ver()[0] == "glibc":
        assert allocator.tune() is True  # glibc accepted every mallopt setting


def test_a_checkpoint_of_another_version_is_a_one_line_error(toy_gaussian_project, tmp_path):
    """A checkpoint whose settings hold a key this avatarctl does not know (written by another version): `eval` and
    `fit --resume` refuse it in one line that says so, not with an internal error."""
    import shutil

    import torch

    from avatarctl.fit.checkpoint import read_checkpoint

    proj = tmp_path / "proj"
    shutil.copytree(toy_gaussian_project, proj)
    path = proj / "fit" / "checkpoints" / "latest.pt"
    path = path.resolve() if path.is_symlink() else path
    ckpt = read_checkpoint(path)
    ckpt["model_config"]["gaussians"]["future_option"] = 1
    ckpt["fit_config"]["model"]["gaussians"]["future_option"] = 1
    torch.save(ckpt, path)
    for args in (["eval", str(proj)], ["fit", str(proj), "--resume", "--iters", "99"]):
        res = CliRunner().invoke(app, args)
        out = res.output.strip()
        assert res.exit_code != 0 and "not ones this avatarctl reads" in out and "future_option" in out, out
        assert "internal error" not in out and "Traceback" not in out, out


def test_warp_is_quiet_unless_debugging(tmp_path):
    """Issue 49: a command that runs Warp kernels (synth: anny's skinning, the cloth solver, the ray caster) prints
    neither Warp's banner and per-module lines nor, on a machine without a CUDA driver, Warp's native warning about
    it; with --debug Warp speaks as it does by itself."""
    def run(*extra: str) -> str:
        res = subprocess.run([sys.executable, "-m", "avatarctl", *extra, "synth", str(tmp_path / f"s{len(extra)}"),
                              "--preset", "micro"], capture_output=True, text=True, timeout=600)
        assert res.returncode == 0, res.stderr[-2000:]
        return res.stdout + res.stderr

    quiet = run()
    assert "Warp " not in quiet and "CUDA driver" not in quiet and "load on device" not in quiet, quiet[-2000:]
    assert "initialized:" in run("--debug")
