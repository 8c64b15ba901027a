"""How far a project's estimated masks are from the true ones, and what that costs a perfect avatar under `eval`.

Two projects of the same frames and cameras: PROJECT, whose masks ingest estimated (MediaPipe, refined against the
plate), and TRUTH, the same capture ingested with its true masks (a synth capture's clean twin, or its `gt/masks`
ingested with `--masks files`; for a phone video, the video's `gt/capture` ingested with `--views cam00`). For every
view both have:

- **IoU** of the two masks;
- **false positives / negatives** as shares of the true foreground's pixels, split by their distance to the true
  outline: ring 1 (the first pixel outside / inside it), ring 2, ring 3 and beyond;
- **masked-frame PSNR**: TRUTH's frame over its true mask against the same frame over PROJECT's mask (both over
  black, `evaluate.protocols.ground_truth`), on the box of both masks. A render that drew the person perfectly
  would score at most this against PROJECT's masks: every pixel the estimated mask cuts off the person is black in
  the ground truth `eval` scores against, every pixel it adds holds the room. The figure is the mean over views of
  each view's PSNR, like `eval`'s headline (but on the masks' box, not the body's).

    python -m benchmarks.mask_accuracy PROJECT TRUTH [--split all|train|test] [--json OUT.json]

`--split test`: the images of PROJECT's split that `eval` scores (novel_view: the held-out views on the training
frames; novel_pose: the held-out views on the held-out frames), `train`: the training views' training frames, `all`
(default): every view and frame both projects hold.
"""

from __future__ import annotations

import argparse
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

RINGS = ("1", "2", "3+")  # distance to the true outline, pixels


@dataclass(frozen=True)
class MaskAccuracyReport:
    split: str
    images: int  # views compared
    iou: float  # mean over views
    false_positive: dict[str, float]  # ring -> estimated-only pixels / true foreground pixels (pooled), by ring
    false_negative: dict[str, float]  # ring -> true-only pixels / true foreground pixels (pooled), by ring
    masked_frame_psnr: float  # mean over views, dB (module docstring)

    @property
    def false_positive_total(self) -> float:
        return float(sum(self.false_positive.values()))

    @property
    def false_negative_total(self) -> float:
        return float(sum(self.false_negative.values()))


def _rings(distance: np.ndarray) -> list[np.ndarray]:
    """[H, W] distance (px) of each pixel to the other side of the outline -> one bool mask per `RINGS` entry."""
    return [(distance > 0) & (distance < 1.5), (distance >= 1.5) & (distance < 2.5), distance >= 2.5]


def _views(capture, split: str) -> list[tuple[str, int]]:
    s = capture.split
    if split == "test":  # eval's novel_view (held-out views, training frames) and novel_pose images
        trained = set(s.train_views)
        novel_view = [(v, f) for v in s.test_views if v not in trained for f in s.train_frames]
        return novel_view + [(v, f) for v in s.test_views for f in s.test_frames]
    if split == "train":
        return [(v, f) for v in s.train_views for f in s.train_frames]
    return [(v, f) for v in sorted(capture.cameras) for f in capture.frames]


def measure(project_dir: str | Path, truth_dir: str | Path, split: str = "all") -> MaskAccuracyReport:
    import cv2

    from avatarctl.evaluate.metrics import psnr
    from avatarctl.evaluate.protocols import ground_truth
    from avatarctl.ingest.masks import iou
    from avatarctl.io.project_io import load_project_capture
    from avatarctl.project import Project

    est = load_project_capture(Project.open(project_dir))
    tru = load_project_capture(Project.open(truth_dir))
    held = set(tru.frames)
    views = [(v, f) for v, f in _views(est, split) if v in tru.cameras and f in held]
    if not views:
        raise SystemExit(f"{project_dir} and {truth_dir} share no view of the {split!r} split: ingest the same "
                         "capture twice (estimated masks, true masks)")
    ious, psnrs = [], []
    fp, fn, fg = np.zeros(len(RINGS)), np.zeros(len(RINGS)), 0
    for v, f in views:
        m, t = est.mask(v, f).astype(bool), tru.mask(v, f).astype(bool)
        if m.shape != t.shape:
            raise SystemExit(f"{v} frame {f}: masks of {m.shape} and {t.shape} px; ingest both at one scale")
        ious.append(iou(m, t))
        fg += int(t.sum())
        outside = cv2.distanceTransform((~t).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
        inside = cv2.distanceTransform(t.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
        fp += [int((m & r).sum()) for r in _rings(np.where(t, 0.0, outside))]
        fn += [int((~m & r).sum()) for r in _rings(np.where(t, inside, 0.0))]
        both = m | t
        if both.any():
            ys, xs = np.nonzero(both)
            box = (slice(ys.min(), ys.max() + 1), slice(xs.min(), xs.max() + 1))
            frame = tru.image(v, f)
            psnrs.append(psnr(ground_truth(frame, m, 0.0)[box], ground_truth(frame, t, 0.0)[box]))
    share = {k: float(x / max(fg, 1)) for k, x in zip(RINGS, fp)}
    miss = {k: float(x / max(fg, 1)) for k, x in zip(RINGS, fn)}
    finite = [p for p in psnrs if np.isfinite(p)]
    return MaskAccuracyReport(split=split, images=len(views), iou=float(np.mean(ious)), false_positive=share,
                              false_negative=miss, masked_frame_psnr=float(np.mean(finite)) if finite else float("inf"))


def main(argv: list[str] | None = None) -> MaskAccuracyReport:
    from avatarctl.atomic import write_json

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("project", help="the project whose masks were estimated")
    ap.add_argument("truth", help="the same capture ingested with its true masks")
    ap.add_argument("--split", default="all", choices=("all", "train", "test"))
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args(argv)
    r = measure(a.project, a.truth, a.split)
    pct = lambda d: " / ".join(f"{100 * x:.2f}" for x in d.values())  # noqa: E731
    print(f"{r.images} views ({r.split}): IoU {r.iou:.4f}; false positives {100 * r.false_positive_total:.2f} % of the "
          f"true foreground (rings {'/'.join(RINGS)} px: {pct(r.false_positive)}), false negatives "
          f"{100 * r.false_negative_total:.2f} % ({pct(r.false_negative)}); masked-frame PSNR "
          f"{r.masked_frame_psnr:.2f} dB (a perfect render against the frame over these masks, masks' box)")
    if a.json is not None:
        write_json(a.json, asdict(r) | {"protocol": "mask_accuracy: masks' box, per-view mean PSNR"})
    return r


if __name__ == "__main__":
    main()
