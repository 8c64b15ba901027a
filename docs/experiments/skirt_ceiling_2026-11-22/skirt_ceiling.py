"""Where the bbox-protocol error of a synth-small avatar comes from: the skirt vs everything else.

Not part of the package; needs a synth capture (its `gt/geometry.npz` has the garment mesh per frame) and the
project `avatarctl ingest` made from it. The skirt's pixels are its mesh rasterised with the project's undistorted
cameras (occlusion by arms ignored), grown by one pixel so its silhouette edge counts as skirt.

    # split the error of rendered images into skirt / rest, and score each image again with its skirt pixels
    # replaced by the ground truth blurred by a Gaussian of sigma px. PNGS: PROJECT/eval/NAME/renders (from
    # `avatarctl eval P --save-images`) or PROJECT/render/NAME/frames (from `avatarctl render P --views ...`)
    python skirt_ceiling.py decompose PROJECT PNGS CAPTURE
    # the ground truth alone: skirt-interior PSNR of its best flat colour and of blurred copies of itself
    python skirt_ceiling.py gt PROJECT CAPTURE

Scores follow `avatarctl eval --protocol bbox`: ground truth = undistorted frame * mask (black background), PSNR
over the projected 3D box of the posed body grown by 5 cm. Pooled figures average the squared error over all box
pixels of all images (not the mean of per-image PSNRs that `avatarctl eval` reports).
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np

from avatarctl.evaluate.metrics import to_float
from avatarctl.evaluate.protocols import bbox_region
from avatarctl.geometry.silhouette import rasterize_silhouette
from avatarctl.io.project_io import load_project_capture
from avatarctl.project import Project

SIGMAS = (1.0, 1.5, 2.0)


def _db(mse: float) -> float:
    return float(-10 * np.log10(mse))


class Frames:
    def __init__(self, project: Path, capture: Path):
        self.cap = load_project_capture(Project.open(project))
        self.geo = dict(np.load(capture / "gt" / "geometry.npz"))

    def gt(self, cam: str, frame: int) -> tuple[np.ndarray, np.ndarray]:
        """(ground truth [H, W, 3] in [0, 1] over black, mask [H, W] bool) as avatarctl eval composes them."""
        mask = self.cap.mask(cam, frame)
        return to_float(self.cap.image(cam, frame)) * mask[..., None], mask

    def box(self, cam: str, frame: int) -> np.ndarray:
        return bbox_region(self.cap.cameras[cam], self.geo["body_vertices"][frame]).mask

    def skirt(self, cam: str, frame: int) -> np.ndarray:
        """[H, W] uint8 0/1: the skirt mesh's silhouette (pixels at least half covered, as ingest rasterises)."""
        return rasterize_silhouette(self.cap.cameras[cam], self.geo["garment_vertices"][frame].astype(np.float64),
                                    self.geo["garment_faces"]).astype(np.uint8)


def decompose(project: Path, render_dir: Path, capture: Path) -> None:
    fr = Frames(project, capture)
    tot = {"skirt": 0.0, "rest": 0.0, "n": 0, "n_skirt": 0, **{s: 0.0 for s in SIGMAS}}
    pngs = sorted(render_dir.glob("*.png"))
    for png in pngs:
        parts = png.stem.split("_")  # eval/NAME/renders: <frame>_<view>; render/NAME/frames: <seq>_<view>_<frame>
        frame, cam = (int(parts[0]), parts[1]) if len(parts) == 2 else (int(parts[2]), parts[1])
        img = to_float(cv2.imread(str(png))[..., ::-1])
        gt, _ = fr.gt(cam, frame)
        box = fr.box(cam, frame)
        sk = cv2.dilate(fr.skirt(cam, frame), np.ones((3, 3), np.uint8)).astype(bool) & box
        err = ((img - gt) ** 2).mean(-1)
        n, e_sk, e_rest = int(box.sum()), float(err[sk].sum()), float(err[box & ~sk].sum())
        print(f"{png.name}: bbox PSNR {_db((e_sk + e_rest) / n):.2f} dB; skirt {sk.sum() / n:.1%} of box pixels, "
              f"{e_sk / (e_sk + e_rest):.1%} of the squared error; skirt {_db(e_sk / sk.sum()):.2f} dB, rest "
              f"{_db(e_rest / (n - sk.sum())):.2f} dB")
        for s in SIGMAS:
            sub = img.copy()
            sub[sk] = cv2.GaussianBlur(gt, (0, 0), s)[sk]
            tot[s] += float(((sub - gt) ** 2).mean(-1)[box].sum())
        tot["skirt"] += e_sk
        tot["rest"] += e_rest
        tot["n"] += n
        tot["n_skirt"] += int(sk.sum())
    n, ns = tot["n"], tot["n_skirt"]
    print(f"pooled over {len(pngs)} images: bbox PSNR {_db((tot['skirt'] + tot['rest']) / n):.2f} dB; skirt "
          f"{ns / n:.1%} of box pixels and {tot['skirt'] / (tot['skirt'] + tot['rest']):.1%} of the squared error; "
          f"skirt {_db(tot['skirt'] / ns):.2f} dB, rest {_db(tot['rest'] / (n - ns)):.2f} dB; with a perfect skirt "
          f"{_db(tot['rest'] / n):.2f} dB; with the skirt := ground truth blurred by sigma "
          + " / ".join(f"{s:g}" for s in SIGMAS) + " px: " + " / ".join(f"{_db(tot[s] / n):.2f}" for s in SIGMAS)
          + " dB")


def gt_only(project: Path, capture: Path, frames=(0, 20, 40, 60), cams=("cam01", "cam04", "cam07", "cam10")) -> None:
    fr = Frames(project, capture)
    acc: dict[str, list[float]] = {}
    for frame in frames:
        for cam in cams:
            gt, mask = fr.gt(cam, frame)
            interior = cv2.erode(fr.skirt(cam, frame), np.ones((3, 3), np.uint8)).astype(bool)
            sk = interior & fr.box(cam, frame) & mask
            px = gt[sk]
            acc.setdefault("best flat colour", []).append(float(((px - px.mean(0)) ** 2).mean()))
            for s in SIGMAS:
                acc.setdefault(f"blurred, sigma {s:g} px", []).append(
                    float(((cv2.GaussianBlur(gt, (0, 0), s)[sk] - px) ** 2).mean()))
    print(f"skirt interior, frames {list(frames)} x views {list(cams)} (pooled MSE):")
    for k, v in acc.items():
        print(f"  {k}: {_db(float(np.mean(v))):.2f} dB")


if __name__ == "__main__":
    mode, args = sys.argv[1], [Path(a) for a in sys.argv[2:]]
    decompose(*args) if mode == "decompose" else gt_only(*args)
