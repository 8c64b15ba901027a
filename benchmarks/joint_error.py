"""Joint and vertex error of a project's body fits against the true ones, before and after the fit's pose refinement.

Joints: the posed centres M_j c_j (`body.joints`; centres solved from the true poses, the fit's shape: the pose
error alone, where `benchmarks.keypoint_offsets --fits` counts the shape too) of the major joints
(`body.joints.major_joints`: 14 for anny);
vertices: the template skinned with the refined / plain / true transforms. The major-joint error vector is also split
into its mean over frames (an offset all frames share) and the rest (frame-to-frame scatter); the corrections' RMS
rotation per refined joint is given with the part all frames share. Training frames only (the refinement's).
Used for docs/fit.md, "Pose refinement" (issue 13: synth --fit-noise captures, true fits in CAPTURE/gt/motion.npz).

    python -m benchmarks.joint_error PROJECT TRUE_MOTION.npz [--json OUT.json]
"""

from __future__ import annotations

import argparse
import json
from dataclasses import asdict, dataclass
from pathlib import Path

import torch


@dataclass(frozen=True)
class PoseError:
    """The error of one set of joint transforms against the true ones, centimetres (means over frames)."""

    name: str  # "fits as given" | "refined"
    joint_cm: float  # major joints
    joint_all_cm: float  # every joint
    vertex_cm: float  # skinned template vertices
    shared_cm: float  # major joints: the offset all frames share (norm of the mean error vector)
    scatter_cm: float  # major joints: the rest, frame to frame


@dataclass(frozen=True)
class JointErrorReport:
    frames: int  # training frames measured
    major_joints: int
    refined: bool  # the fit has pose refinement (else "refined" repeats "fits as given")
    errors: tuple[PoseError, ...]  # fits as given, refined
    correction_rms_deg: float | None  # RMS correction per refined joint, degrees (None without refinement)
    correction_shared_deg: float | None  # ... of it, the part all frames share


def measure(project: Path, true_motion: Path) -> JointErrorReport:
    from avatarctl.body.joints import joint_centres, major_joints, posed_joints, skin_weighted_centroids
    from avatarctl.body.lbs import lbs
    from avatarctl.body.motion import BodyMotion
    from avatarctl.fit.checkpoint import load_avatar
    from avatarctl.project import Project

    av = load_avatar(Project.open(project), device="cpu")
    frames = sorted(int(f) for f in av.train_frames)
    motion = av.capture.motion.for_frames(frames)
    truth = BodyMotion.load(true_motion)
    truth = truth.for_frames(frames)
    tpl = av.body.template(motion)
    M_fit = av.body.pose(motion).joint_transforms.double()
    M_true = av.body.pose(truth).joint_transforms.double()
    c = joint_centres(M_true, tpl.parents, skin_weighted_centroids(tpl.vertices, tpl.skin_weights).double())
    major = major_joints(tpl.skin_weights)
    cond = av.conditioning(motion, frames_are_training=True)
    ref = av.model.pose_refine
    with torch.no_grad():
        M_ref = ref(cond.joint_transforms, cond.frame_ids).double() if ref is not None else M_fit
    x_true = posed_joints(M_true, c)
    V = tpl.vertices.double()
    W = tpl.skin_weights.double()
    v_true = lbs(V, W, M_true)
    errors = []
    for name, M in (("fits as given", M_fit), ("refined", M_ref)):
        e = (posed_joints(M, c) - x_true).norm(dim=-1)
        ve = (lbs(V, W, M) - v_true).norm(dim=-1)
        d = (posed_joints(M, c) - x_true)[:, major]  # [frames, joints, 3]: the offset all frames share + the rest
        shared = d.mean(0, keepdim=True)
        errors.append(PoseError(name=name, joint_cm=float(100 * e[:, major].mean()), joint_all_cm=float(100 * e.mean()),
                                vertex_cm=float(100 * ve.mean()), shared_cm=float(100 * shared.norm(dim=-1).mean()),
                                scatter_cm=float(100 * (d - shared).norm(dim=-1).mean())))
    rms = shared_deg = None
    if ref is not None:
        delta = ref.delta.detach()[:, ref.active]  # [frames, refined joints, 3] radians

        def rms_deg(x: torch.Tensor) -> float:
            return float(x.norm(dim=-1).pow(2).mean().sqrt().rad2deg())

        rms, shared_deg = rms_deg(delta), rms_deg(delta.mean(0))
    return JointErrorReport(frames=len(frames), major_joints=int(major.sum()), refined=ref is not None,
                            errors=tuple(errors), correction_rms_deg=rms, correction_shared_deg=shared_deg)


def format_report(project: Path, r: JointErrorReport) -> str:
    lines = [f"{project}: {r.frames} training frames, {r.major_joints} major joints"
             + ("" if r.refined else " (no pose refinement in this fit)")]
    for e in r.errors:
        lines.append(f"  {e.name:14s} joint error {e.joint_cm:.2f} cm (all joints {e.joint_all_cm:.2f} cm), "
                     f"vertex error {e.vertex_cm:.2f} cm; major joints: shared by all frames "
                     f"{e.shared_cm:.2f} cm, frame to frame {e.scatter_cm:.2f} cm")
    if r.refined:
        lines.append(f"  corrections: RMS per refined joint {r.correction_rms_deg:.2f} deg, of which shared by all "
                     f"frames {r.correction_shared_deg:.2f} deg")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> JointErrorReport:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("project", type=Path)
    ap.add_argument("true_motion", type=Path, help="the true body fits (a BodyMotion .npz, e.g. CAPTURE/gt/motion.npz)")
    ap.add_argument("--json", type=Path, default=None, help="also write the figures as JSON here")
    args = ap.parse_args(argv)
    report = measure(args.project, args.true_motion)
    print(format_report(args.project, report))
    if args.json is not None:
        args.json.write_text(json.dumps(asdict(report), indent=2) + "\n")
    return report


if __name__ == "__main__":
    main()
