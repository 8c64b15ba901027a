"""How much of a perturbation does plain temporal smoothing of the fits remove? (experiment tooling, no training)

Each Gaussian width: the given fits' anny pose parameters smoothed over the training frames (rotations averaged
then projected back onto rotations, translations averaged), and the mean error of the 14 major joints and of the
vertices against the truth; the truth smoothed the same way says what smoothing costs a true motion.

    python smooth_probe.py CAPTURE_WITH_PERTURBED_FITS [TRAIN_FRAMES]     # truth read from CAPTURE/gt/motion.npz
"""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from avatarctl.body.joints import joint_centres, posed_joints, skin_weighted_centroids
from avatarctl.body.lbs import lbs
from avatarctl.body.motion import BodyMotion
from avatarctl.body.registry import load_body_model
from avatarctl.io.gt_geometry import GT_MOTION


def smooth(m: BodyMotion, sigma: float) -> BodyMotion:
    from scipy.ndimage import gaussian_filter1d

    P = m.pose_parameters.astype(np.float64).copy()  # [F, J, 4, 4]
    Q = gaussian_filter1d(P, sigma, axis=0, mode="nearest")
    U, _, Vt = np.linalg.svd(Q[..., :3, :3])
    P[..., :3, :3], P[..., :3, 3] = U @ Vt, Q[..., :3, 3]
    return replace(m, pose_parameters=P.astype(np.float32))


def main(capture: Path, train_frames: int = 80) -> None:
    frames = list(range(train_frames))
    given, truth = (BodyMotion.load(p) for p in (capture / "motion.npz", capture / GT_MOTION))
    given, truth = given.select(given.rows_for(frames)), truth.select(truth.rows_for(frames))
    body = load_body_model("anny")
    tpl = body.template(truth)
    M_true = body.pose(truth).joint_transforms.double()
    c = joint_centres(M_true, tpl.parents, skin_weighted_centroids(tpl.vertices, tpl.skin_weights).double())
    mass = tpl.skin_weights.sum(0)
    major = mass > 0.01 * mass.sum()
    V, W = tpl.vertices.double(), tpl.skin_weights.double()
    x_true, v_true = posed_joints(M_true, c), lbs(V, W, M_true)

    def error(m: BodyMotion) -> str:
        M = body.pose(m).joint_transforms.double()
        e = (posed_joints(M, c) - x_true).norm(dim=-1)[:, major].mean()
        ve = (lbs(V, W, M) - v_true).norm(dim=-1).mean()
        return f"joints {100 * float(e):.2f} cm, vertices {100 * float(ve):.2f} cm"

    print(f"{capture}: given fits {error(given)}")
    with torch.no_grad():
        for sigma in (0.7, 1.0, 1.5, 2.0, 3.0):
            print(f"  smoothed, sigma {sigma} frames: given {error(smooth(given, sigma))}; "
                  f"the truth smoothed alike {error(smooth(truth, sigma))}")


if __name__ == "__main__":
    main(Path(sys.argv[1]), *(int(x) for x in sys.argv[2:]))
