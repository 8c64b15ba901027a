"""Which capture format a folder holds (``--format auto``), with the evidence, checked in this order:

========================  =====================================================================
actorshq                  ``calibration.csv`` + ``rgbs/`` (a scale folder), or a sequence folder holding one
                          ``Nx/calibration.csv`` (``avatarctl.io.actorshq``)
dna_rendering             a ``<seq>.smc`` file (its ``<seq>_annots.smc`` beside it or in the release's
                          annotations folder; ``avatarctl.io.dna_rendering``)
4d_dress                  ``Capture/cameras.pkl`` + ``basic_info.pkl`` (a 4D-DRESS take folder)
zju                       ``annots.npy``
thuman4                   ``calibration.json``
peoplesnapshot            ``camera.pkl`` (and ``masks.hdf5``)
easymocap                 ``intri.yml`` + ``extri.yml`` (also what ``avatarctl synth`` writes)
colmap                    ``sparse/0/cameras.bin|txt``, ``sparse/cameras.*`` or ``cameras.*``
video                     a video file, or a folder of image files with no calibration (checked first;
                          ``avatarctl.io.monocular``: one static camera)
========================  =====================================================================
"""

from __future__ import annotations

from pathlib import Path

from avatarctl.errors import InputError

FORMATS = ("easymocap", "zju", "thuman4", "peoplesnapshot", "colmap", "actorshq", "dna_rendering", "4d_dress")


def detect_format(root: str | Path) -> tuple[str, str]:
    """(format, reason) for the capture folder `root`; InputError if it is not a known layout."""
    from avatarctl.io.actorshq import is_actorshq
    from avatarctl.io.monocular import is_monocular_source

    root = Path(root)
    if is_monocular_source(root):
        return "video", ("a video file" if root.is_file() else "a folder of frames without calibration") + \
            ": one static camera"
    if not root.is_dir():
        raise InputError("capture folder not found", where=str(root), fix="pass the folder that holds the capture")
    if is_actorshq(root):
        return "actorshq", "found calibration.csv + rgbs/ (ActorsHQ)"
    smc = sorted(p.name for p in root.glob("*.smc") if not p.name.endswith("_annots.smc"))
    if smc:
        return "dna_rendering", f"found {smc[0]} (DNA-Rendering)"
    if (root / "Capture" / "cameras.pkl").is_file() and (root / "basic_info.pkl").is_file():
        return "4d_dress", "found Capture/cameras.pkl + basic_info.pkl (4D-DRESS)"
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
                         "(THuman4.0), camera.pkl (PeopleSnapshot), sparse/0/cameras.bin (COLMAP), "
                         "calibration.csv + rgbs/ (ActorsHQ, its scale folder e.g. Sequence1/4x), <seq>.smc "
                         "(DNA-Rendering) or Capture/cameras.pkl + basic_info.pkl (4D-DRESS); "
                         "or pass --format")
