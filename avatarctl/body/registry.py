"""`load_body_model(name, path)`: the one way stages obtain a body model."""

from __future__ import annotations

from pathlib import Path

from avatarctl.body.base import BodyModel
from avatarctl.errors import InputError


FILE_FREE = ("anny", "toy")  # body models that need no model file


def needs_model_file(name: str) -> bool:
    """smpl / smplx need the user's licensed model file; anny and the toy sphere do not."""
    return name not in FILE_FREE


def load_body_model(name: str, path: str | Path | None = None, device: str = "cpu") -> BodyModel:
    """anny (free, default) needs no file; smpl / smplx need the user's model file (.pkl or .npz); toy is the
    two-joint sphere of the tests (avatarctl.body.toy)."""
    if name == "anny":
        from avatarctl.body.anny_model import AnnyBody

        return AnnyBody(device=device)
    if name == "toy":
        from avatarctl.body.toy import ToyBody

        return ToyBody()
    if name in ("smpl", "smplx"):
        if path is None:
            raise InputError(f"the {name} body model needs its model file",
                             fix=f"pass --body-model-path /path/to/{name.upper()}_NEUTRAL.pkl (or .npz); "
                                 "avatarctl never ships licensed SMPL files")
        p = Path(path)
        if not p.is_file():
            raise InputError(f"{name} model file not found", where=str(p), fix="check --body-model-path")
        from avatarctl.body.smpl import SmplBody

        return SmplBody.from_file(p, kind=name, device=device)
    raise InputError(f"unknown body model {name!r}", fix="use one of: anny, smpl, smplx")
