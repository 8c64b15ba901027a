"""`resolve_device`: the one rule turning a `--device` option into a `torch.device` (fit, render, eval, demo)."""

from __future__ import annotations

from typing import TYPE_CHECKING

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
