"""One reader per capture format -> `CaptureSource`, and the EasyMocap layout reader.

EasyMocap layout (also what ``avatarctl synth`` writes)::

    intri.yml, extri.yml            cameras (see avatarctl/io/easymocap.py)
    images/<cam>/%06d.jpg           frames (distorted, as captured), or
    videos/<cam>.mp4                one video per camera (frame number = 0-based frame index; avatarctl/io/video.py)
    masks/<cam>/%06d.png            optional masks (> 127 foreground; 'mask/' also accepted)
    background/<cam>.jpg|png        optional background plates (for --masks background)
    motion.npz | smpl/%06d.json     optional body fits: BodyMotion npz, or EasyMocap SMPL Rh/Th json (without
                                    them ingest estimates anny fits from keypoints: --fits keypoints)
    split.json                      optional train/test split (avatarctl Split json)
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Callable

from avatarctl.errors import InputError
from avatarctl.io.capture import CaptureSource, FileImages, FileMasks, first_image_sizes, scan_numbered
from avatarctl.io.project_io import Split


def read_capture_split(root: Path) -> Split | None:
    """The capture's own ``split.json`` (avatarctl `Split` json), or None."""
    p = Path(root) / "split.json"
    if not p.is_file():
        return None
    try:
        return Split.from_json(json.loads(p.read_text()))
    except (OSError, json.JSONDecodeError, KeyError, TypeError, ValueError) as e:
        raise InputError(f"cannot read split.json ({type(e).__name__}: {e})", where=str(p),
                         fix="expected {train_frames, test_frames, train_views, test_views}") from None


def read_easymocap(root: Path) -> CaptureSource:
    from avatarctl.io.easymocap import read_easymocap_cameras
    from avatarctl.io.easymocap_fits import has_capture_fits, read_capture_fits

    root = Path(root)
    img_root = root / "images"
    if not img_root.is_dir() and (root / "videos").is_dir():
        per_cam, sizes, images, fps = _read_videos(root / "videos")
    elif not img_root.is_dir():
        raise InputError("no images/ or videos/ folder", where=str(root),
                         fix="EasyMocap captures keep frames in images/<cam>/%06d.jpg or videos/<cam>.mp4")
    else:
        per_cam = {d.name: scan_numbered(d) for d in sorted(img_root.iterdir()) if d.is_dir()}
        sizes = first_image_sizes(per_cam)
        images, fps = None, 0.0
    cameras = read_easymocap_cameras(root, image_size=sizes)
    names = [c.name for c in cameras]
    for c in cameras:
        if c.name in sizes and sizes[c.name] != (c.width, c.height):
            raise InputError(f"camera {c.name}: images are {sizes[c.name][0]}x{sizes[c.name][1]} but intri.yml says "
                             f"{c.width}x{c.height}", where=str(root / "intri.yml"),
                             fix=f"fix W_{c.name}/H_{c.name} or the images")
    image_frames = {n: set(per_cam.get(n, {})) for n in names}
    if images is None:
        images = FileImages({(n, f): p for n in names for f, p in per_cam.get(n, {}).items()})
    mask_root = next((d for d in (root / "masks", root / "mask") if d.is_dir()), None)
    masks = mask_frames = None
    if mask_root is not None:
        mper = {n: scan_numbered(mask_root / n) for n in names}
        mask_frames = {n: set(d) for n, d in mper.items()}
        masks = FileMasks({(n, f): p for n, d in mper.items() for f, p in d.items()})
    bgs = {n: p for n in names for p in [root / "background" / f"{n}.jpg", root / "background" / f"{n}.png"]
           if p.is_file()}
    fits, fits_where = read_capture_fits(root) if has_capture_fits(root) else (None, "")
    return CaptureSource(format="easymocap", root=root, cameras=cameras, image_frames=image_frames, images=images,
                         fits=fits, fits_where=fits_where, masks=masks, mask_frames=mask_frames, backgrounds=bgs,
                         split=read_capture_split(root), uncalibrated=sorted(set(per_cam) - set(names)),
                         fps=fps)


def _read_videos(folder: Path) -> tuple[dict[str, dict[int, Path]], dict[str, tuple[int, int]], "VideoImages", float]:
    """videos/<cam>.mp4 -> ({cam: {frame: video}}, {cam: (width, height)}, reader, frame rate)."""
    from avatarctl.io.video import VideoImages, scan_videos, video_info

    vids = scan_videos(folder)
    if not vids:
        raise InputError("videos/ holds no video files", where=str(folder),
                         fix="add one video per camera named after it, e.g. videos/01.mp4")
    infos = {c: video_info(p) for c, p in vids.items()}
    per_cam = {c: {f: p for f in range(infos[c].frames)} for c, p in vids.items()}
    sizes = {c: (i.width, i.height) for c, i in infos.items()}
    fps = next(iter(infos.values())).fps
    return per_cam, sizes, VideoImages(paths=vids, sizes=sizes), fps


def reader_for(fmt: str) -> Callable[[Path], CaptureSource]:
    """The reader function of a format name (see avatarctl.io.detect.FORMATS)."""
    if fmt == "easymocap":
        return read_easymocap
    if fmt == "zju":
        from avatarctl.io.zju import read_zju

        return read_zju
    if fmt == "thuman4":
        from avatarctl.io.thuman4 import read_thuman4

        return read_thuman4
    if fmt == "peoplesnapshot":
        from avatarctl.io.peoplesnapshot import read_peoplesnapshot

        return read_peoplesnapshot
    if fmt == "colmap":
        from avatarctl.io.colmap import read_colmap

        return read_colmap
    if fmt == "actorshq":
        from avatarctl.io.actorshq import read_actorshq

        return read_actorshq
    if fmt == "dna_rendering":
        from avatarctl.io.dna_rendering import read_dna_rendering

        return read_dna_rendering
    if fmt == "4d_dress":
        from avatarctl.io.four_d_dress import read_four_d_dress

        return read_four_d_dress
    from avatarctl.io.detect import FORMATS

    raise InputError(f"unknown capture format {fmt!r}", fix=f"use --format auto, {', '.join(FORMATS)}")
