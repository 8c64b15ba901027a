"""ZJU-MoCap captures (Neural Body's release).

Layout::

    annots.npy                     pickled dict: cams {K [3x3], D [5x1], R [3x3], T [3x1] MILLIMETRES} (lists, one
                                   per camera) and ims: list over frames of {'ims': [image path per camera]}
    Camera_B1/000000.jpg ...       images (CoreView_313/315: 'Camera (1)/CoreView_313_Camera_(1)_0001_<time>.jpg',
                                   1-based frame number in the 5th '_' field)
    mask_cihp/<image path>.png     masks (value != 0 is foreground); 'mask/' is used when mask_cihp/ is absent
    new_params/<frame>.npy         SMPL fits {poses (1,72) first 3 zero, Rh (1,3), Th (1,3) metres, shapes (1,10)};
    params/<frame>.npy             'new_params' (refit with pose blend shapes) is preferred when present

Camera translations are converted from millimetres to metres. Frame number = the image file's number (0-based).
annots.npy and the params are pickles: they are read with `avatarctl.safe_pickle` (numpy arrays and plain
containers only; anything else, e.g. a payload calling os.system, is refused before it runs).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from avatarctl.errors import InputError
from avatarctl.io.capture import CaptureSource, FileImages, FileMasks, RhThFits, make_camera, safe_camera_name
from avatarctl.io.easymocap_fits import rhth_from_records
from avatarctl.safe_pickle import load_npy


def zju_frame_number(rel: str) -> int:
    """Frame number of a ZJU image path: '000123.jpg' -> 123; 313/315 '..._Camera_(1)_0001_...jpg' -> 0."""
    stem = Path(rel).stem
    if stem.isdigit():
        return int(stem)
    parts = stem.split("_")
    if len(parts) > 4 and parts[4].isdigit():
        return int(parts[4]) - 1
    raise InputError(f"cannot read a frame number from image name {rel!r}", where="annots.npy",
                     fix="name images <frame>.jpg (or the CoreView_313/315 pattern)")


def read_zju(root: Path) -> CaptureSource:
    root = Path(root)
    apath = root / "annots.npy"
    annots = load_npy(apath, "annots.npy")
    if not isinstance(annots, dict) or "cams" not in annots or "ims" not in annots:
        raise InputError("annots.npy has no 'cams'/'ims' entries", where=str(apath),
                         fix="expected Neural Body's annots.npy: {'cams': {K, D, R, T}, 'ims': [{'ims': [...]}]}")
    cams_d, ims = annots["cams"], annots["ims"]
    try:
        Ks, Ds, Rs, Ts = (list(cams_d[k]) for k in ("K", "D", "R", "T"))
    except (KeyError, TypeError):
        raise InputError("annots.npy 'cams' needs K, D, R and T lists", where=str(apath),
                         fix="one entry per camera in each list") from None
    ncam = len(Ks)
    if not (len(Ds) == len(Rs) == len(Ts) == ncam) or ncam == 0:
        raise InputError(f"annots.npy lists {len(Ks)} K, {len(Ds)} D, {len(Rs)} R, {len(Ts)} T", where=str(apath),
                         fix="every camera needs K, D, R and T")
    if not ims or not isinstance(ims[0], dict) or "ims" not in ims[0]:
        raise InputError("annots.npy 'ims' is empty or malformed", where=str(apath),
                         fix="expected a list over frames of {'ims': [image path per camera]}")

    # camera folder names from the first frame's image paths
    first = list(ims[0]["ims"])
    if len(first) != ncam:
        raise InputError(f"annots.npy frame 0 lists {len(first)} images for {ncam} calibrated cameras",
                         where=str(apath), fix="the 'ims' lists must have one image per calibrated camera")
    folders = [Path(p).parent.as_posix() for p in first]
    names = [safe_camera_name(f) for f in folders]
    if len(set(names)) != ncam:
        raise InputError("annots.npy image paths do not give one folder per camera", where=str(apath),
                         fix="store each camera's images in its own folder")

    images: dict[tuple[str, int], Path] = {}
    masks: dict[tuple[str, int], Path] = {}
    mask_root = root / "mask_cihp" if (root / "mask_cihp").is_dir() else root / "mask"
    image_frames: dict[str, set[int]] = {n: set() for n in names}
    mask_frames: dict[str, set[int]] = {n: set() for n in names}
    for entry in ims:
        paths = list(entry["ims"])
        if len(paths) != ncam:
            raise InputError(f"annots.npy has a frame with {len(paths)} images for {ncam} cameras",
                             where=str(apath), fix="every frame must list one image per camera")
        for n, rel in zip(names, paths):
            f = zju_frame_number(rel)
            p = root / rel
            if p.is_file():
                images[(n, f)] = p
                image_frames[n].add(f)
            mp = (mask_root / rel).with_suffix(".png")
            if mp.is_file():
                masks[(n, f)] = mp
                mask_frames[n].add(f)

    cameras = []
    for i, n in enumerate(names):
        K = np.asarray(Ks[i], dtype=np.float64)
        T_mm = np.asarray(Ts[i], dtype=np.float64).reshape(3)
        size = _image_size(images, n)
        cameras.append(make_camera(apath, name=n, K=K, R=np.asarray(Rs[i], dtype=np.float64), T=T_mm / 1000.0,
                                   width=size[0], height=size[1], dist=np.asarray(Ds[i], dtype=np.float64).ravel()))

    fits = read_zju_params(root)
    has_masks = any(mask_frames.values())
    notes = [f"camera T converted from millimetres to metres ({ncam} cameras)",
             f"fits from {Path(fits.where).name}/"]
    if has_masks:
        notes.append(f"masks from {mask_root.name}/ (value != 0 is foreground)")
    uncal = sorted(p.name for p in root.glob("Camera*") if p.is_dir() and safe_camera_name(p.name) not in names)
    return CaptureSource(format="zju", root=root, cameras=cameras, image_frames=image_frames,
                         images=FileImages(images), fits=fits, fits_where=fits.where,
                         masks=FileMasks(masks, threshold=0) if has_masks else None,
                         mask_frames=mask_frames if has_masks else None, uncalibrated=uncal, notes=notes)


def _image_size(images: dict[tuple[str, int], Path], cam: str) -> tuple[int, int]:
    """(width, height) from the camera's first image (ZJU stores no image size)."""
    import cv2

    for (c, _f), p in sorted(images.items(), key=lambda kv: kv[0][1]):
        if c == cam:
            img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
            if img is None:
                raise InputError(f"image unreadable or corrupt: camera {cam}", where=str(p),
                                 fix="re-export this image")
            return int(img.shape[1]), int(img.shape[0])
    return 0, 0  # a camera without images; ingest reports it when it is selected


def read_zju_params(root: Path) -> RhThFits:
    """``new_params/`` (preferred) or ``params/``: ``<frame>.npy`` dicts {Rh, Th, poses, shapes}."""
    folder = root / "new_params" if (root / "new_params").is_dir() else root / "params"
    if not folder.is_dir():
        raise InputError("no SMPL fits (params/ or new_params/)", where=str(root),
                         fix="ZJU-MoCap captures need params/<frame>.npy with Rh, Th, poses, shapes")
    records = []
    for p in sorted(folder.glob("*.npy")):
        if not p.stem.isdigit():
            continue
        d = load_npy(p, "fit file")
        if not isinstance(d, dict):
            raise InputError("fit file is not a dict {Rh, Th, poses, shapes}", where=str(p), fix="re-export it")
        records.append((int(p.stem), d, str(p)))
    return rhth_from_records(records, str(folder))
