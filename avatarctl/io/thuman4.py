"""THuman4.0 captures (the paper's own multi-view data).

Layout::

    calibration.json          {camXX: {K (9 values, row-major), R (9), T (3) metres, imgSize [W, H], optional D}}
                              world -> camera
    images/camXX/%08d.jpg     frames
    masks/camXX/%08d.jpg      masks (gray > 128 is foreground, JPEG)
    missing_img_files.txt     optional: image files absent from the release (one relative path per line);
                              a frame missing in any camera is left out of every camera
    smpl_params.npz           SMPL-X fits, one row per frame: betas, global_orient, transl, body_pose (63),
                              jaw_pose, expression, left/right_hand_pose (45, full axis-angle)

Frame number = the image file's number; row r of smpl_params.npz is frame r.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from avatarctl.body.motion import BodyMotion
from avatarctl.errors import InputError
from avatarctl.io.capture import CaptureSource, FileImages, FileMasks, make_camera, safe_camera_name, scan_numbered
from avatarctl.geometry.cameras import Camera


def _vec(d: dict, key: str, n: int, cam: str, where: Path) -> np.ndarray:
    try:
        a = np.asarray(d[key], dtype=np.float64).ravel()
    except (KeyError, TypeError, ValueError):
        raise InputError(f"camera {cam} has no numeric {key!r}", where=str(where),
                         fix="calibration.json needs K (9), R (9), T (3), imgSize [W, H] per camera") from None
    if a.size != n:
        raise InputError(f"camera {cam}: {key} has {a.size} values, expected {n}", where=str(where),
                         fix="K and R are 3x3 (9 values), T has 3")
    return a


def read_thuman4_cameras(path: Path) -> list[Camera]:
    try:
        calib = json.loads(Path(path).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise InputError(f"cannot parse calibration.json ({type(e).__name__})", where=str(path),
                         fix="re-download it") from None
    if not isinstance(calib, dict) or not calib:
        raise InputError("calibration.json has no cameras", where=str(path), fix="expected {camXX: {K, R, T, imgSize}}")
    cams = []
    for name in sorted(calib):
        d = calib[name]
        K = _vec(d, "K", 9, name, path).reshape(3, 3)
        R = _vec(d, "R", 9, name, path).reshape(3, 3)
        T = _vec(d, "T", 3, name, path)
        W, H = (int(v) for v in _vec(d, "imgSize", 2, name, path))
        dist = np.asarray(d.get("D", d.get("dist", np.zeros(5))), dtype=np.float64).ravel()
        cams.append(make_camera(path, name=safe_camera_name(name), K=K, R=R, T=T, width=W, height=H, dist=dist))
    return cams


def _missing_files(root: Path) -> set[tuple[str, int]]:
    """(camera, frame) pairs listed in missing_img_files.txt."""
    p = root / "missing_img_files.txt"
    out: set[tuple[str, int]] = set()
    if not p.is_file():
        return out
    for line in p.read_text().splitlines():
        line = line.strip().replace("\\", "/")
        if not line:
            continue
        parts = Path(line).parts
        if len(parts) >= 2 and Path(parts[-1]).stem.isdigit():
            out.add((safe_camera_name(parts[-2]), int(Path(parts[-1]).stem)))
    return out


def read_thuman4_fits(path: Path) -> BodyMotion:
    path = Path(path)
    if not path.is_file():
        raise InputError("no SMPL-X fits", where=str(path), fix="THuman4.0 captures need smpl_params.npz")
    try:
        with np.load(path, allow_pickle=False) as z:
            d = {k: np.asarray(z[k], dtype=np.float64) for k in z.files}
    except (ValueError, OSError) as e:
        raise InputError(f"cannot read smpl_params.npz ({type(e).__name__})", where=str(path),
                         fix="re-download it") from None
    for key in ("global_orient", "transl", "body_pose", "betas"):
        if key not in d:
            raise InputError(f"smpl_params.npz has no {key!r}", where=str(path),
                             fix="expected betas, global_orient, transl, body_pose (SMPL-X)")
    n = d["global_orient"].reshape(d["global_orient"].shape[0], -1).shape[0]

    def rows(key: str, dim: int) -> np.ndarray | None:
        if key not in d:
            return None
        a = d[key].reshape(d[key].shape[0], -1) if d[key].ndim > 1 else d[key].reshape(1, -1)
        if a.shape != (n, dim):
            raise InputError(f"smpl_params.npz {key} has shape {d[key].shape}, expected ({n}, {dim})",
                             where=str(path), fix=f"write {key} with {dim} values per frame (hands: full 45, no PCA)")
        if not np.isfinite(a).all():
            raise InputError(f"smpl_params.npz {key} contains NaN or inf", where=str(path),
                             fix="re-run the fitting for those frames")
        return a

    betas = d["betas"].reshape(-1, d["betas"].shape[-1])[0]
    expr = d.get("expression")
    kw = dict(global_orient=rows("global_orient", 3), transl=rows("transl", 3), body_pose=rows("body_pose", 63),
              jaw_pose=rows("jaw_pose", 3), left_hand_pose=rows("left_hand_pose", 45),
              right_hand_pose=rows("right_hand_pose", 45),
              expression=rows("expression", expr.reshape(expr.shape[0], -1).shape[1]) if expr is not None else None)
    try:
        return BodyMotion(body_model="smplx", frame_index=np.arange(n), betas=betas, **kw)
    except ValueError as e:
        raise InputError(f"bad SMPL-X fits: {e}", where=str(path), fix="check the array shapes") from None


def read_thuman4(root: Path) -> CaptureSource:
    root = Path(root)
    cameras = read_thuman4_cameras(root / "calibration.json")
    names = [c.name for c in cameras]
    missing = _missing_files(root)
    images: dict[tuple[str, int], Path] = {}
    masks: dict[tuple[str, int], Path] = {}
    image_frames: dict[str, set[int]] = {}
    mask_frames: dict[str, set[int]] = {}
    for n in names:
        found = {f: p for f, p in scan_numbered(root / "images" / n).items() if (n, f) not in missing}
        image_frames[n] = set(found)
        images.update({(n, f): p for f, p in found.items()})
        mfound = scan_numbered(root / "masks" / n)
        mask_frames[n] = set(mfound)
        masks.update({(n, f): p for f, p in mfound.items()})
    # frames listed as missing in one camera are dropped from all cameras
    dropped = {f for (_c, f) in missing}
    for n in names:
        image_frames[n] -= dropped
    has_masks = any(mask_frames.values())
    img_dir = root / "images"
    uncal = sorted(p.name for p in img_dir.iterdir() if p.is_dir() and p.name not in names) if img_dir.is_dir() else []
    notes = []
    if dropped:
        notes.append(f"{len(dropped)} frames listed in missing_img_files.txt left out")
    return CaptureSource(format="thuman4", root=root, cameras=cameras, image_frames=image_frames,
                         images=FileImages(images), fits=read_thuman4_fits(root / "smpl_params.npz"),
                         fits_where=str(root / "smpl_params.npz"),
                         masks=FileMasks(masks, threshold=128) if has_masks else None,
                         mask_frames=mask_frames if has_masks else None, uncalibrated=uncal, notes=notes)
