"""`resolve_device`: the one rule turning a `--device` option into a `torch.device` (fit, render, eval, demo); and
`init_warp`: Warp initialised the one way (quietly under the CLI, `quiet_warp`)."""

from __future__ import annotations

import os
from typing import TYPE_CHECKING, Any

from avatarctl.errors import InputError

if TYPE_CHECKING:
    import torch


def resolve_device(device: str) -> "torch.device":
    """'auto' -> cuda when available, else cpu; 'cuda' without a GPU is an `InputError`."""
    import torch

    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise InputError("--device cuda requested but torch sees no CUDA device", fix="use --device cpu or auto")
    try:
        return torch.device(device)
    except RuntimeError:
        raise InputError(f"unknown device {device!r}", fix="use auto, cpu or cuda") from None


_WARP_NOISE = (b"Could not find or load the NVIDIA CUDA driver",)  # normal on a CPU machine: not worth a line
WARP_QUIET_ENV = "AVATARCTL_QUIET_WARP"  # "1" (set by the CLI unless --debug): `init_warp` initialises it quietly


_warp_ready = False  # init_warp ran in this process


def init_warp() -> Any:
    """The `warp` module, initialised: quietly (`quiet_warp`) when `AVATARCTL_QUIET_WARP` is "1" (the CLI sets it
    unless `--debug`), else as Warp does by itself. Called before avatarctl's (and anny's) kernels (the rasterizer
    on every call: after the first, only the import's lookup)."""
    global _warp_ready
    import warp as wp

    if not _warp_ready:
        if os.environ.get(WARP_QUIET_ENV) == "1":
            quiet_warp()
        else:
            wp.init()
        _warp_ready = True
    return wp


def quiet_warp() -> None:
    """Initialise Warp (kernels: `avatarctl/splat`, the synth's cloth, anny's skinning) with its console output off:
    the 8-line banner and the line per compiled module (Warp's INFO log level) and, on a machine without a CUDA
    driver, the native warning about it (printed by Warp's C code to file descriptor 2 during `wp.init`, so that
    descriptor is caught for the call; any other line it printed is passed on). Idempotent; a Warp already
    initialised is left as it is."""
    import sys
    import tempfile

    import warp as wp

    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as caught:
        os.dup2(caught.fileno(), 2)
        try:
            wp.init()
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        caught.seek(0)
        for line in caught.read().splitlines(keepends=True):
            if not any(noise in line for noise in _WARP_NOISE):
                os.write(2, line)
