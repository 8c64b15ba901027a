"""DNA-Rendering captures (Cheng et al., ICCV 2023): one sequence, released as two SMC (HDF5) files.

Layout followed: the official `SMCReader` and 3DGS loader of DNA-Rendering/DNA-Rendering at commit 2691286
(`scripts/3DGS/SMCReader.py`, `scripts/3DGS/dataset_readers.py` `readCamerasDNARendering`), cross-checked with
SeqAvatar's `process_dnarendering.py` (zezeaaa/SeqAvatar c598982: the 12 MP cameras and their masks)::

    CAPTURE/<seq>.smc                      main file (the release's dna_rendering_partN_main/<seq>.smc)
      Camera_5mp/<id>/color/<frame>        encoded image bytes (JPEG; cv2.imdecode gives BGR), cameras '0'..'47'
      Camera_12mp/<id>/color/<frame>       cameras '48'..'59' (ids are global: '48', not '0'); another image size
      attrs                                actor_id, performance_id, gender, ...
    <seq>_annots.smc                       annotations: beside the main file, or where the release puts it
                                           (the sibling folder with 'main' -> 'annotations' in its name)
      Camera_Parameter/<id:02d>/K [3, 3]   pixels;  D [5] k1 k2 p1 p2 k3;  RT [4, 4] CAMERA -> WORLD (inverted here:
                                           OpenCV world -> camera, metres);  Color_Calibration [3, 3] (not applied,
                                           as the official loader does not)
      Mask/<id>/mask/<frame>               encoded mask bytes (decoded as colour, max over channels; > 127 foreground)
      SMPLx/fullpose [F, 55, 3]            axis-angle: 0 global_orient, 1-21 body, 22 jaw, 23-24 eyes, 25-39 left
                                           hand, 40-54 right hand (smplx `flat_hand_mean=False`: offsets from the
                                           model's hand mean); transl [F, 3] metres; betas [F, 10] (averaged);
                                           expression [F, 10]; scale (ignored, as every public loader does)

Quirks: calibration keys are zero-padded ('03'), image and mask keys are not ('3'); frame keys are decimal strings
('0'..'149'; row r of SMPLx is frame r). Camera names in the project are the two-digit ids ('03', '48').
Nothing is loaded whole: cameras and fits are read at once, every image / mask is decoded from its own HDF5 dataset
when ingest asks for that (camera, frame).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from avatarctl.body.motion import BodyMotion
from avatarctl.errors import InputError
from avatarctl.geometry.cameras import Camera
from avatarctl.io.capture import CaptureSource, fmt_list, make_camera

IMAGE_GROUPS = ("Camera_5mp", "Camera_12mp")
ANNOTS_SUFFIX = "_annots.smc"
MASK_THRESHOLD = 127
_FULLPOSE_JOINTS = 55


def camera_name(cam_id: int) -> str:
    """The project name of DNA-Rendering camera `cam_id`: the calibration's two-digit key ('03', '48')."""
    return f"{int(cam_id):02d}"


def find_smc_pair(root: Path) -> tuple[Path, Path]:
    """(main file, annotations file) of the one sequence in `root`; one-line errors name what is missing."""
    root = Path(root)
    mains = sorted(p for p in root.glob("*.smc") if not p.name.endswith(ANNOTS_SUFFIX))
    if not mains:
        raise InputError("no DNA-Rendering main file (<seq>.smc)", where=str(root),
                         fix="put the sequence's <seq>.smc (from dna_rendering_partN_main/) in the capture folder")
    if len(mains) > 1:
        raise InputError(f"{len(mains)} DNA-Rendering sequences in one folder ({fmt_list([p.name for p in mains])})",
                         where=str(root), fix="make one folder per sequence holding <seq>.smc and <seq>_annots.smc "
                                              "(symbolic links are fine)")
    main = mains[0]
    name = main.stem + ANNOTS_SUFFIX
    candidates = [root / name]
    if "main" in root.name:
        candidates.append(root.parent / root.name.replace("main", "annotations") / name)
    for c in candidates:
        if c.is_file():
            return main, c
    raise InputError(f"annotations file {name} missing (cameras, masks and SMPL-X fits are in it)",
                     where=" or ".join(str(c) for c in candidates),
                     fix=f"put {name} (from dna_rendering_partN_annotations/) beside {main.name}")


def _open(path: Path) -> Any:
    import h5py

    try:
        return h5py.File(path, "r")
    except OSError as e:
        raise InputError(f"cannot open {path.name} as HDF5 ({' '.join(str(e).split())[:120]})", where=str(path),
                         fix="re-download it (an SMC file is HDF5; a partial download does not open)") from None


def _ids(group: Any) -> dict[int, str]:
    """{camera or frame number: HDF5 key} for the decimal keys of `group` (padded or not)."""
    return {int(k): k for k in group.keys() if str(k).isdigit()}


def _decode(data: np.ndarray, what: str, where: str) -> np.ndarray:
    """BGR uint8 [H, W, 3] from an encoded image stored as a uint8 dataset."""
    import cv2

    img = cv2.imdecode(np.asarray(data, dtype=np.uint8).ravel(), cv2.IMREAD_COLOR)
    if img is None or img.size == 0:
        raise InputError(f"{what} cannot be decoded", where=where, fix="re-download the SMC file")
    return img


@dataclass
class _SmcDatasets:
    """One SMC file, opened on the first `load` and kept open; `paths` maps (camera, frame) to the HDF5 dataset of
    one encoded image."""

    path: Path
    paths: dict[tuple[str, int], str]  # (camera name, frame) -> HDF5 dataset path
    _file: Any = field(default=None, repr=False)

    def load(self, cam: str, frame: int, what: str) -> np.ndarray:
        key = self.paths.get((cam, frame))
        if key is None:
            raise InputError(f"no {what} for camera {cam}, frame {frame}", where=str(self.path),
                             fix="leave the frame out with --frames or the camera with --views")
        if self._file is None:
            self._file = _open(self.path)
        where = f"{self.path}[{key}]"
        try:
            data = self._file[key][()]
        except (KeyError, OSError) as e:
            raise InputError(f"{what} unreadable: camera {cam}, frame {frame} ({type(e).__name__})", where=where,
                             fix="re-download the SMC file") from None
        return _decode(data, f"{what} of camera {cam}, frame {frame}", where)

    def where(self, cam: str, frame: int) -> str:
        return f"{self.path}[{self.paths.get((cam, frame), f'camera {cam} frame {frame}')}]"


@dataclass
class SmcImages:
    """Images of the main file, decoded per (camera, frame): RGB uint8 [H, W, 3] (the file stores BGR JPEG)."""

    data: _SmcDatasets

    def read(self, cam: str, frame: int) -> np.ndarray:
        return np.ascontiguousarray(self.data.load(cam, frame, "image")[..., ::-1])

    def where(self, cam: str, frame: int) -> str:
        return self.data.where(cam, frame)


@dataclass
class SmcMasks:
    """Masks of the annotations file, decoded per (camera, frame): bool [H, W], max over channels > 127."""

    data: _SmcDatasets

    def read(self, cam: str, frame: int) -> np.ndarray:
        return self.data.load(cam, frame, "mask").max(axis=-1) > MASK_THRESHOLD

    def where(self, cam: str, frame: int) -> str:
        return self.data.where(cam, frame)


def _array(group: Any, key: str, where: str, cam: str) -> np.ndarray:
    if key not in group:
        raise InputError(f"camera {cam} has no {key!r} in Camera_Parameter", where=where,
                         fix="expected K [3, 3], D [5], RT [4, 4] per camera: re-download the annotations file")
    return np.asarray(group[key][()], dtype=np.float64)


def read_dna_rendering_cameras(annots: Any, where: str, sizes: dict[str, tuple[int, int]]) -> list[Camera]:
    """Cameras of `Camera_Parameter` (open annotations file) with an image size in `sizes` (name -> (W, H)), in id
    order; `RT` (camera -> world) is inverted to OpenCV world -> camera."""
    if "Camera_Parameter" not in annots:
        raise InputError("the annotations file has no Camera_Parameter group", where=where,
                         fix="re-download <seq>_annots.smc")
    cams = []
    for cid, key in sorted(_ids(annots["Camera_Parameter"]).items()):
        name = camera_name(cid)
        if name not in sizes:
            continue  # calibrated but no images in the main file
        g = annots["Camera_Parameter"][key]
        K, D, RT = _array(g, "K", where, name), _array(g, "D", where, name).ravel(), _array(g, "RT", where, name)
        if K.shape != (3, 3) or RT.shape != (4, 4):
            raise InputError(f"camera {name}: K {K.shape} / RT {RT.shape}, expected (3, 3) / (4, 4)", where=where,
                             fix="re-download the annotations file")
        try:
            w2c = np.linalg.inv(RT)
        except np.linalg.LinAlgError:
            raise InputError(f"camera {name}: RT is singular", where=where, fix="re-download the annotations file") \
                from None
        W, H = sizes[name]
        cams.append(make_camera(where, name=name, K=K, R=w2c[:3, :3], T=w2c[:3, 3], width=W, height=H, dist=D))
    return cams


def read_dna_rendering_fits(annots: Any, where: str) -> tuple[BodyMotion | None, list[str]]:
    """The `SMPLx` group as an SMPL-X `BodyMotion` (one row per frame, frame r = row r), and notes."""
    if "SMPLx" not in annots:
        return None, ["the annotations file has no SMPLx group: no fits (ingest can estimate them: --fits keypoints)"]
    g = annots["SMPLx"]
    missing = [k for k in ("fullpose", "transl", "betas") if k not in g]
    if missing:
        raise InputError(f"SMPLx lacks {', '.join(missing)}", where=where,
                         fix="expected SMPLx/fullpose [F, 55, 3], transl [F, 3], betas [F, 10], expression [F, 10]")
    full = np.asarray(g["fullpose"][()], dtype=np.float64)
    n = full.shape[0] if full.ndim else 0
    full = full.reshape(n, -1)
    if full.shape[1] != _FULLPOSE_JOINTS * 3:
        raise InputError(f"SMPLx fullpose has shape {g['fullpose'].shape}, expected ({n}, 55, 3)", where=where,
                         fix="re-download the annotations file")
    transl = np.asarray(g["transl"][()], dtype=np.float64).reshape(n, -1) if n else np.zeros((0, 3))
    betas = np.asarray(g["betas"][()], dtype=np.float64)
    betas = betas.reshape(-1, betas.shape[-1]) if betas.ndim else betas.reshape(1, 1)
    expr = np.asarray(g["expression"][()], dtype=np.float64).reshape(n, -1) if "expression" in g else None
    if transl.shape != (n, 3) or betas.shape[0] not in (1, n) or (expr is not None and expr.shape[0] != n):
        raise InputError(f"SMPLx arrays disagree: fullpose {n} frames, transl {g['transl'].shape}, betas "
                         f"{g['betas'].shape}", where=where, fix="re-download the annotations file")
    if not (np.isfinite(full).all() and np.isfinite(transl).all() and np.isfinite(betas).all()):
        raise InputError("SMPLx contains NaN or inf", where=where, fix="re-download the annotations file")
    notes = []
    if "scale" in g:
        s = float(np.asarray(g["scale"][()]).ravel()[0])
        if abs(s - 1.0) > 1e-3:
            notes.append(f"SMPLx scale {s:.4f} ignored (as the official loader does)")
    pose = full.reshape(n, _FULLPOSE_JOINTS, 3)
    motion = BodyMotion(body_model="smplx", frame_index=np.arange(n), global_orient=pose[:, 0],
                        body_pose=pose[:, 1:22].reshape(n, 63), jaw_pose=pose[:, 22], leye_pose=pose[:, 23],
                        reye_pose=pose[:, 24], left_hand_pose=pose[:, 25:40].reshape(n, 45),
                        right_hand_pose=pose[:, 40:55].reshape(n, 45), transl=transl, betas=betas.mean(axis=0),
                        expression=expr)
    notes.append("SMPL-X hand poses are offsets from the model's hand mean (smplx flat_hand_mean=False): ingest adds "
                 "the model file's mean")
    return motion, notes


def _image_size(main: Any, key: str, where: str) -> tuple[int, int]:
    """(width, height) of one encoded image, read from its header without decoding the pixels (Pillow: imageio and
    scikit-image require it)."""
    import io

    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(io.BytesIO(np.asarray(main[key][()], dtype=np.uint8).tobytes())) as im:
            return int(im.size[0]), int(im.size[1])
    except (UnidentifiedImageError, OSError, ValueError):
        raise InputError("image cannot be decoded", where=f"{where}[{key}]", fix="re-download the SMC file") from None


def read_dna_rendering(root: Path) -> CaptureSource:
    root = Path(root)
    main_path, annots_path = find_smc_pair(root)
    notes: list[str] = []
    image_paths: dict[tuple[str, int], str] = {}
    image_frames: dict[str, set[int]] = {}
    sizes: dict[str, tuple[int, int]] = {}
    with _open(main_path) as main:
        groups = [g for g in IMAGE_GROUPS if g in main]
        if not groups:
            raise InputError(f"the main file has no {' or '.join(IMAGE_GROUPS)} group", where=str(main_path),
                             fix="pass the sequence's main file (dna_rendering_partN_main/<seq>.smc)")
        for grp in groups:
            for cid, ckey in sorted(_ids(main[grp]).items()):
                name = camera_name(cid)
                if "color" not in main[grp][ckey]:
                    continue
                frames = _ids(main[grp][ckey]["color"])
                image_frames[name] = set(frames)
                image_paths.update({(name, f): f"{grp}/{ckey}/color/{k}" for f, k in frames.items()})
                if frames:
                    sizes[name] = _image_size(main, image_paths[(name, min(frames))], str(main_path))
    with _open(annots_path) as annots:
        cameras = read_dna_rendering_cameras(annots, str(annots_path), sizes)
        names = [c.name for c in cameras]
        mask_paths: dict[tuple[str, int], str] = {}
        mask_frames: dict[str, set[int]] | None = None
        if "Mask" in annots:
            by_id = {camera_name(cid): key for cid, key in _ids(annots["Mask"]).items()}
            mask_frames = {}
            for n in names:
                g = annots["Mask"][by_id[n]] if n in by_id else None
                frames = _ids(g["mask"]) if g is not None and "mask" in g else {}
                mask_frames[n] = set(frames)
                mask_paths.update({(n, f): f"Mask/{by_id[n]}/mask/{k}" for f, k in frames.items()})
        else:
            notes.append("the annotations file has no Mask group")
        fits, fit_notes = read_dna_rendering_fits(annots, str(annots_path))
    notes += fit_notes
    if not cameras:
        raise InputError("no camera has both images (main file) and a calibration (annotations file)",
                         where=str(root), fix="check that <seq>.smc and <seq>_annots.smc are of the same sequence")
    notes.append(f"{len(cameras)} cameras: images from {main_path.name}; calibration, masks and fits from "
                 f"{annots_path.name}")
    has_masks = bool(mask_frames) and any(mask_frames.values())
    return CaptureSource(format="dna_rendering", root=root, cameras=cameras,
                         image_frames={n: image_frames.get(n, set()) for n in names},
                         images=SmcImages(_SmcDatasets(main_path, image_paths)), fits=fits,
                         fits_where=f"{annots_path}[SMPLx]",
                         masks=SmcMasks(_SmcDatasets(annots_path, mask_paths)) if has_masks else None,
                         mask_frames=mask_frames if has_masks else None,
                         uncalibrated=sorted(set(image_frames) - set(names)), notes=notes,
                         hands_from_mean=True)
