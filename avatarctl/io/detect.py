"""Which capture format a folder holds (``--format auto``), with the evidence, checked in this order:

========================  =====================================================================
zju                       ``annots.npy``
thuman4                   ``calibration.json``
peoplesnapshot            ``camera.pkl`` (and ``masks.hdf5``)
easymocap                 ``intri.yml`` + ``extri.yml`` (also what ``avatarctl synth`` writes)
colmap                    ``sparse/0/cameras.bin|txt``, ``sparse/cameras.*`` or ``cameras.*``
========================  =====================================================================
"""

from __future__ import annotations

from pathlib import Path

from avatarctl.errors import InputError

FORMATS = ("easymocap", "zju", "thuman4", "peoplesnapshot", "colmap")


def detect_format(root: str | Path) -> tuple[str, str]:
    """(format, reason) for the capture folder `root`; InputError if it is not a known layout."""
    root = Path(root)
    if not root.is_dir():
        raise InputError("capture folder not found", where=str(root), fix="pass the folder that holds the capture")
    if (root / "annots.npy").is_file():
        return "zju", "found annots.npy (ZJU-MoCap)"
    if (root / "calibration.json").is_file():
        return "thuman4", "found calibration.json (THuman4.0)"
    if (root / "camera.pkl").is_file():
        return "peoplesnapshot", "found camera.pkl (PeopleSnapshot)"
    if (root / "intri.yml").is_file() and (root / "extri.yml").is_file():
        return "easymocap", "found intri.yml + extri.yml (EasyMocap)"
    for d in (root / "sparse" / "0", root / "sparse", root):
        for ext in ("bin", "txt"):
            if (d / f"cameras.{ext}").is_file():
                rel = (d / f"cameras.{ext}").relative_to(root).as_posix()
                return "colmap", f"found {rel} (COLMAP)"
    raise InputError("unknown capture format", where=str(root),
                     fix="expected intri.yml+extri.yml (EasyMocap), annots.npy (ZJU-MoCap), calibration.json "
                         "(THuman4.0), camera.pkl (PeopleSnapshot) or sparse/0/cameras.bin (COLMAP); "
                         "or pass --format")
