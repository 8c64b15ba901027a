"""Mean joint and vertex error of a project's body fits against the true ones, before and after the fit's pose
refinement (experiment tooling).

Joints: the posed centres M_j c_j (`body.joints`, centres solved from the true poses) of the "major" joints, those
carrying at least 1 % of the template's skinning weight (14 for anny: hips, feet, spine, upper/lower arms, head);
vertices: the template skinned with the refined / plain / true transforms. The major-joint error vector is also split
into its mean over frames (an offset all frames share) and the rest (frame-to-frame scatter), and the corrections'
RMS rotation per refined joint is printed with the part all frames share.

    python joint_error.py PROJECT TRUE_MOTION.npz
"""

from __future__ import annotations

import sys
from pathlib import Path

import torch

from avatarctl.body.joints import joint_centres, posed_joints, skin_weighted_centroids
from avatarctl.body.lbs import lbs
from avatarctl.body.motion import BodyMotion
from avatarctl.fit.checkpoint import load_avatar
from avatarctl.project import Project


def main(project: Path, true_motion: Path) -> None:
    av = load_avatar(Project.open(project), device="cpu")
    frames = sorted(int(f) for f in av.train_frames)
    motion = av.capture.motion.select(av.capture.motion.rows_for(frames))
    truth = BodyMotion.load(true_motion)
    truth = truth.select(truth.rows_for(frames))
    tpl = av.body.template(motion)
    M_fit = av.body.pose(motion).joint_transforms.double()
    M_true = av.body.pose(truth).joint_transforms.double()
    c = joint_centres(M_true, tpl.parents, skin_weighted_centroids(tpl.vertices, tpl.skin_weights).double())
    mass = tpl.skin_weights.sum(0)
    major = mass > 0.01 * mass.sum()
    cond = av.conditioning(motion, frames_are_training=True)
    ref = av.model.pose_refine
    with torch.no_grad():
        M_ref = ref(cond.joint_transforms, cond.frame_ids).double() if ref is not None else M_fit
    x_true = posed_joints(M_true, c)
    V = tpl.vertices.double()
    W = tpl.skin_weights.double()
    v_true = lbs(V, W, M_true)
    print(f"{project}: {len(frames)} training frames, {int(major.sum())} major joints"
          + ("" if ref is not None else " (no pose refinement in this fit)"))
    for name, M in (("fits as given", M_fit), ("refined", M_ref)):
        e = (posed_joints(M, c) - x_true).norm(dim=-1)
        ve = (lbs(V, W, M) - v_true).norm(dim=-1)
        d = (posed_joints(M, c) - x_true)[:, major]  # [T, J, 3]: the offset all frames share + the rest
        shared = d.mean(0, keepdim=True)
        print(f"  {name:14s} joint error {100 * e[:, major].mean():.2f} cm (all joints {100 * e.mean():.2f} cm), "
              f"vertex error {100 * ve.mean():.2f} cm; major joints: shared by all frames "
              f"{100 * shared.norm(dim=-1).mean():.2f} cm, frame to frame "
              f"{100 * (d - shared).norm(dim=-1).mean():.2f} cm")
    if ref is not None:
        delta = ref.delta.detach()[:, ref.active]  # [T, refined joints, 3] radians

        def rms_deg(x: torch.Tensor) -> float:
            return float(x.norm(dim=-1).pow(2).mean().sqrt().rad2deg())

        print(f"  corrections: RMS per refined joint {rms_deg(delta):.2f} deg, of which shared by all frames "
              f"{rms_deg(delta.mean(0)):.2f} deg")


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]))
