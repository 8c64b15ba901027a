"""The box PSNR a synth-small avatar could reach with its garment rendered as well as X and the rest as rendered (or
perfect). Not part of the package. Uses the renders `avatarctl eval P --save-images` keeps and the capture's
ground-truth geometry (the garment region of `avatarctl eval --region`, evaluate/regions.py).

    python ceiling.py PROJECT EVAL_NAME
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np

from avatarctl.evaluate.metrics import to_float
from avatarctl.evaluate.protocols import bbox_region, ground_truth
from avatarctl.evaluate.regions import garment_mask
from avatarctl.io.gt_geometry import find_gt_geometry, load_gt_geometry
from avatarctl.io.project_io import load_project_capture
from avatarctl.project import Project


def db(m: float) -> float:
    return float(-10 * np.log10(m))


def main(project: Path, name: str) -> None:
    proj = Project.open(project)
    cap = load_project_capture(proj)
    geo = load_gt_geometry(find_gt_geometry(proj.manifest.source.path))
    cases = {"as rendered": [], "garment := its best flat colour": [],
             "garment := flat colour, rest perfect": [], "garment := GT blurred 1 px": [],
             "garment := GT blurred 2 px": [], "garment := GT blurred 4 px": [], "garment perfect": []}
    for png in sorted((project / "eval" / name / "renders").glob("*.png")):
        frame, view = int(png.stem.split("_")[0]), png.stem.split("_")[1]
        cam = cap.cameras[view].pinhole()
        r = geo.row(frame)
        box = bbox_region(cam, geo.body_vertices[r]).mask
        gm = garment_mask(cam, geo.body_vertices[r], geo.body_faces, geo.garment_vertices[r], geo.garment_faces) & box
        img = to_float(cv2.imread(str(png))[..., ::-1])
        gt = ground_truth(cap.image(view, frame), cap.mask(view, frame), (0, 0, 0))
        err = ((img - gt) ** 2).mean(-1)
        flat = ((gt[gm] - gt[gm].mean(0)) ** 2).mean(-1)
        n = box.sum()
        rest = err[box & ~gm].sum()
        cases["as rendered"].append(err[box].sum() / n)
        cases["garment := its best flat colour"].append((rest + flat.sum()) / n)
        cases["garment := flat colour, rest perfect"].append(flat.sum() / n)
        for s in (1, 2, 4):
            b = ((cv2.GaussianBlur(gt, (0, 0), s) - gt) ** 2).mean(-1)
            cases[f"garment := GT blurred {s} px"].append((rest + b[gm].sum()) / n)
        cases["garment perfect"].append(rest / n)
    print(f"{project} eval {name}: {len(cases['as rendered'])} images, mean of per-image box PSNR")
    for k, v in cases.items():
        print(f"  {k:40s} {np.mean([db(m) for m in v]):.2f} dB")


if __name__ == "__main__":
    main(Path(sys.argv[1]), sys.argv[2])
