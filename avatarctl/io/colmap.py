"""Cameras calibrated with COLMAP (read with pycolmap), frames per camera, body fits beside them.

Layout::

    sparse/0/ (or sparse/, or the capture folder itself)   COLMAP model: cameras/images(.bin|.txt), ...
    images/<cam>/%06d.jpg                                   frames of each static camera
    masks/<cam>/%06d.png                                    optional masks (> 127 foreground)
    background/<cam>.jpg                                    optional background plates
    motion.npz | smpl/%06d.json                             body fits in the SAME world frame, metres

Each COLMAP image registers one static camera; its name is ``<cam>/<file>`` (camera = the folder) or
``<cam>.<ext>`` (camera = the stem). COLMAP places pixel centres at +0.5 (top-left pixel centre is (0.5, 0.5));
OpenCV at integers, so cx, cy are shifted by -0.5. Supported models: SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL,
RADIAL, OPENCV. COLMAP's scale is arbitrary: the model must be metric (e.g. aligned to a checkerboard).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from avatarctl.errors import InputError
from avatarctl.io.capture import CaptureSource, FileImages, FileMasks, make_camera, safe_camera_name, scan_numbered
from avatarctl.io.easymocap_fits import read_capture_fits
from avatarctl.geometry.cameras import Camera

_MODELS = {  # model name -> function(params) -> (fx, fy, cx, cy, dist[5])
    "SIMPLE_PINHOLE": lambda p: (p[0], p[0], p[1], p[2], [0, 0, 0, 0, 0]),
    "PINHOLE": lambda p: (p[0], p[1], p[2], p[3], [0, 0, 0, 0, 0]),
    "SIMPLE_RADIAL": lambda p: (p[0], p[0], p[1], p[2], [p[3], 0, 0, 0, 0]),
    "RADIAL": lambda p: (p[0], p[0], p[1], p[2], [p[3], p[4], 0, 0, 0]),
    "OPENCV": lambda p: (p[0], p[1], p[2], p[3], [p[4], p[5], p[6], p[7], 0]),
}


def find_sparse_model(root: Path) -> Path | None:
    for d in (root / "sparse" / "0", root / "sparse", root):
        if any((d / f"cameras.{ext}").is_file() for ext in ("bin", "txt")):
            return d
    return None


def read_colmap_cameras(model_dir: Path) -> list[Camera]:
    import pycolmap

    try:
        rec = pycolmap.Reconstruction(str(model_dir))
    except Exception as e:  # noqa: BLE001 - pycolmap raises several types for unreadable models
        raise InputError(f"pycolmap cannot read the sparse model ({type(e).__name__})", where=str(model_dir),
                         fix="check cameras/images .bin|.txt (write them with COLMAP)") from None
    by_name: dict[str, Camera] = {}
    for _iid, img in sorted(rec.images.items(), key=lambda kv: kv[1].name):
        parts = Path(img.name).parts
        cam_name = safe_camera_name(parts[0] if len(parts) > 1 else Path(img.name).stem)
        if cam_name in by_name:
            continue  # several registered images of one static camera: the first (by name) is used
        if not img.has_pose:
            continue
        c = rec.cameras[img.camera_id]
        model = c.model.name
        if model not in _MODELS:
            raise InputError(f"COLMAP camera model {model} is not supported (camera {cam_name})",
                             where=str(model_dir), fix=f"re-run COLMAP with one of {', '.join(_MODELS)}")
        fx, fy, cx, cy, dist = _MODELS[model](np.asarray(c.params, dtype=np.float64))
        pose = img.cam_from_world() if callable(img.cam_from_world) else img.cam_from_world
        K = np.array([[fx, 0, cx - 0.5], [0, fy, cy - 0.5], [0, 0, 1.0]])
        by_name[cam_name] = make_camera(model_dir, name=cam_name, K=K, R=np.asarray(pose.rotation.matrix()),
                                        T=np.asarray(pose.translation), width=int(c.width), height=int(c.height),
                                        dist=np.asarray(dist, dtype=np.float64))
    if not by_name:
        raise InputError("the COLMAP model has no registered images", where=str(model_dir),
                         fix="register one image per camera (name '<cam>/<file>')")
    return [by_name[n] for n in sorted(by_name)]


def read_colmap(root: Path) -> CaptureSource:
    root = Path(root)
    model_dir = find_sparse_model(root)
    if model_dir is None:
        raise InputError("no COLMAP sparse model (cameras.bin/.txt)", where=str(root),
                         fix="put the model in sparse/0/")
    cameras = read_colmap_cameras(model_dir)
    names = [c.name for c in cameras]
    images, masks, image_frames, mask_frames = {}, {}, {}, {}
    for n in names:
        found = scan_numbered(root / "images" / n)
        image_frames[n] = set(found)
        images.update({(n, f): p for f, p in found.items()})
        mfound = scan_numbered(root / "masks" / n)
        mask_frames[n] = set(mfound)
        masks.update({(n, f): p for f, p in mfound.items()})
    has_masks = any(mask_frames.values())
    img_dir = root / "images"
    uncal = sorted(p.name for p in img_dir.iterdir() if p.is_dir() and p.name not in names) if img_dir.is_dir() else []
    bgs = {n: p for n in names for p in [root / "background" / f"{n}.jpg", root / "background" / f"{n}.png"]
           if p.is_file()}
    fits, fits_where = read_capture_fits(root)
    return CaptureSource(format="colmap", root=root, cameras=cameras, image_frames=image_frames,
                         images=FileImages(images), fits=fits, fits_where=fits_where,
                         masks=FileMasks(masks) if has_masks else None,
                         mask_frames=mask_frames if has_masks else None, backgrounds=bgs, uncalibrated=uncal,
                         notes=[f"cameras from COLMAP model {model_dir.relative_to(root).as_posix() or '.'}"])
