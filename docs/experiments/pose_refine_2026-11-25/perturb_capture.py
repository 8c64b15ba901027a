"""Make a perturbed-fit copy of a synth capture without rendering it again (experiment tooling).

`avatarctl synth --fit-noise DEG,CM` renders the capture and then writes motion.npz perturbed by
`body.perturb.perturb_motion(true, DEG, CM, seed)` and the true fits to gt/motion.npz; the images do not depend on
the noise. This script does the same to an existing capture: a hard-linked copy (the source is not modified) whose
motion.npz is replaced, the truth kept in gt/motion.npz.

    python perturb_capture.py SRC DST DEG CM [SEED [CORR_FRAMES]]
"""

from __future__ import annotations

import os
import shutil
import sys
from pathlib import Path

import numpy as np

from avatarctl.body.motion import BodyMotion
from avatarctl.body.perturb import perturb_motion
from avatarctl.io.gt_geometry import GT_MOTION


def main(src: Path, dst: Path, deg: float, cm: float, seed: int = 0, corr_frames: float = 0.0) -> None:
    shutil.copytree(src, dst, copy_function=os.link)
    true = BodyMotion.load(src / "motion.npz")
    extra = {k: v for k, v in np.load(src / "motion.npz").items() if k == "bone_labels"}
    (dst / "motion.npz").unlink()  # a hard link to the source: never write through it
    np.savez(dst / GT_MOTION, **true.to_npz_dict(), **extra)
    noisy = perturb_motion(true, deg, cm, seed=seed, corr_frames=corr_frames)
    np.savez(dst / "motion.npz", **noisy.to_npz_dict(), **extra)
    print(f"{dst}: motion.npz perturbed by {deg} deg / {cm} cm (seed {seed}, drift {corr_frames} frames); truth in {GT_MOTION}")


if __name__ == "__main__":
    a = sys.argv[1:]
    main(Path(a[0]), Path(a[1]), float(a[2]), float(a[3]), int(a[4]) if len(a) > 4 else 0,
         float(a[5]) if len(a) > 5 else 0.0)
