"""Ingest of a large capture in bounded memory: a synthetic capture in the ActorsHQ release layout, generated on the
fly, ingested by the ingest stage while the process's memory is sampled after every frame.

    python -m benchmarks.ingest_memory [--cams 20] [--frames 450] [--size 1024] [--no-contact-sheet] [--keep DIR]
                                       [--out FILE.json]

The capture (`avatarctl.io.actorshq` layout: ``Actor01/Sequence1/4x/`` with calibration.csv, rgbs/, masks/, and a
motion.npz of the toy sphere body beside it) has CAMS cameras on a ring, FRAMES frames of SIZE x SIZE pixels. The
body stands still, so each camera's image and mask are painted once and the same bytes written for every frame:
generating is not what is measured; ingest reads, checks, undistorts and writes every image and mask, hashes every
capture file, poses the body and writes the contact sheet (whose 12 tiles, 4 cameras x 3 frames, are kept until the
end: at 1024² about 20 MB per frame of tiles), as for a real capture. Memory: the resident set size
(/proc/self/statm) after each ingested frame and the process's peak (ru_maxrss); a bounded ingest keeps the RSS
flat from the first frames to the last. Reported: images, seconds (generate, ingest), images per second, peak RSS,
RSS after 10 % / 50 % / 100 % of the frames, and its growth from 10 % to the end.

Generated into a temporary folder that is removed afterwards (``--keep DIR`` writes it there instead and keeps it).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np


@dataclass(frozen=True)
class IngestMemory:
    cams: int
    frames: int
    size: int
    images: int  # cams x frames (each with its mask)
    capture_mb: float  # bytes of the generated capture
    generate_seconds: float
    ingest_seconds: float
    images_per_second: float
    peak_rss_mb: float  # the process's peak RSS (generation included)
    rss_mb: dict[str, float]  # RSS after "10%", "50%", "100%" of the frames were ingested
    rss_growth_mb: float  # RSS after the last frame minus after 10 % of them


def _rss_mb() -> float:
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def _cameras(n: int, size: int) -> list:
    from avatarctl.geometry.cameras import Camera, look_at

    f = size * 1.6
    K = np.array([[f, 0, (size - 1) / 2], [0, f, (size - 1) / 2], [0, 0, 1]])
    cams = []
    for i in range(n):
        a = 2 * np.pi * i / n
        R, T = look_at(np.array([1.6 * np.cos(a), 1.6 * np.sin(a), 0.1 * np.sin(3 * a)]), np.zeros(3))
        cams.append(Camera(name=f"Cam{i + 1:03d}", K=K, R=R, T=T, width=size, height=size))
    return cams


def generate(root: Path, cams: int, frames: int, size: int) -> Path:
    """Write the capture under `root`; returns its scale folder."""
    import cv2

    from avatarctl.body.motion import BodyMotion
    from avatarctl.body.toy import ToyBody
    from avatarctl.geometry.silhouette import rasterize_silhouette
    from avatarctl.io.actorshq import mask_path, rgb_path, write_actorshq_cameras

    seq = root / "Actor01" / "Sequence1"
    scale_dir = seq / "4x"
    scale_dir.mkdir(parents=True)
    cameras = _cameras(cams, size)
    write_actorshq_cameras(scale_dir / "calibration.csv", cameras)
    z = np.zeros((frames, 3), np.float32)
    motion = BodyMotion(body_model="toy", frame_index=np.arange(frames), global_orient=z, body_pose=z, transl=z)
    motion.save(seq / "motion.npz")
    body = ToyBody()
    one = motion.select([0])
    verts = body.pose(one).vertices[0].numpy().astype(np.float64)  # [V, 3]
    faces = body.template(one).faces.numpy()
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32)
    for cam in cameras:
        mask = rasterize_silhouette(cam, verts, faces, supersample=1)
        img = np.stack([90 + 40 * np.sin(xx / 23.0), 110 + 30 * np.cos(yy / 17.0), np.full_like(xx, 130)], -1)
        img[mask] = np.stack([200 - 60 * yy / size, 80 + 40 * np.sin(xx / 5.0), 60 + 0 * xx], -1)[mask]
        jpg = cv2.imencode(".jpg", img.astype(np.uint8)[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 90])[1].tobytes()
        png = cv2.imencode(".png", mask.astype(np.uint8) * 255)[1].tobytes()
        rgb_path(scale_dir, cam.name, 0).parent.mkdir(parents=True)
        mask_path(scale_dir, cam.name, 0).parent.mkdir(parents=True)
        for f in range(frames):
            rgb_path(scale_dir, cam.name, f).write_bytes(jpg)
            mask_path(scale_dir, cam.name, f).write_bytes(png)
    return scale_dir


def main(argv: list[str] | None = None) -> IngestMemory:
    from avatarctl.progress import ProgressReport
    from avatarctl.stages import ingest
    from avatarctl.stages.ingest import IngestConfig

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cams", type=int, default=20)
    ap.add_argument("--frames", type=int, default=450)
    ap.add_argument("--size", type=int, default=1024, help="image width and height, pixels")
    ap.add_argument("--no-contact-sheet", action="store_true", help="ingest without the contact sheet (its tiles)")
    ap.add_argument("--keep", type=Path, default=None, help="generate into this (new) folder and keep it")
    ap.add_argument("--out", type=Path, default=None, help="write the results as JSON here")
    args = ap.parse_args(argv)

    root = args.keep if args.keep is not None else Path(tempfile.mkdtemp(prefix="avatarctl_ingest_memory_"))
    try:
        t0 = time.perf_counter()
        scale_dir = generate(root / "capture", args.cams, args.frames, args.size)
        generated = time.perf_counter() - t0
        capture_mb = sum(p.stat().st_size for p in (root / "capture").rglob("*") if p.is_file()) / 2**20
        samples: dict[int, float] = {}

        def on_progress(p: ProgressReport) -> None:
            if p.part == "frames":
                samples[p.done] = _rss_mb()

        t1 = time.perf_counter()
        proj = root / "project"
        ingest.run(proj, IngestConfig(capture=scale_dir, project=proj, contact_sheet=not args.no_contact_sheet),
                   progress=on_progress)
        seconds = time.perf_counter() - t1
    finally:
        if args.keep is None:
            shutil.rmtree(root, ignore_errors=True)
    n = args.frames

    def at(share: float) -> float:
        return samples[max(1, round(share * n))]

    rss = {"10%": round(at(0.1), 1), "50%": round(at(0.5), 1), "100%": round(at(1.0), 1)}  # MB, as reported
    res = IngestMemory(cams=args.cams, frames=n, size=args.size, images=args.cams * n, capture_mb=round(capture_mb, 3),
                       generate_seconds=round(generated, 2), ingest_seconds=round(seconds, 2),
                       images_per_second=round(args.cams * n / seconds, 2),
                       # the kernel's high-water mark (ru_maxrss), never below a sampled RSS (statm counts pages
                       # a little differently: 0.1 MB apart on a toy run)
                       peak_rss_mb=round(max(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                                             max(samples.values(), default=0.0)), 1),
                       rss_mb=rss,
                       rss_growth_mb=round(rss["100%"] - rss["10%"], 1))  # of the reported figures (was 0.1 apart)
    print(json.dumps(asdict(res), indent=2))
    if args.out is not None:
        args.out.write_text(json.dumps(asdict(res), indent=2))
    return res


if __name__ == "__main__":
    main()
