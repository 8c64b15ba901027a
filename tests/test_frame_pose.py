"""Test-time pose refinement (`fit.frame_pose`, `eval --refine-pose`; issue 51 item 4): a frame rendered by the avatar
itself at a known pose and started 3 cm off is moved back; the avatar's weights do not change; eval reports the
refined figure apart from the plain one (which stays what it is without the refinement), with its own CSV columns,
sheet and table row; the ray-marched fields and a random latent are refused in one line."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import torch


def _frame(project):
    from avatarctl.fit.checkpoint import load_avatar
    from avatarctl.project import Project

    av = load_avatar(Project.open(project), "cpu")
    f = int(av.train_frames[0])
    one = av.capture.motion.for_frames([f])
    return av, av.conditioning(one, frames_are_training=False)


def _views(av, cond, bg):
    """Each training camera's whole image of the frame as the avatar renders it (the target), its alpha as the mask."""
    from avatarctl.fit.frame_pose import PoseView
    from avatarctl.splat import SplatCamera

    state = av.model.node_state(cond, mode="zero")
    out = []
    with torch.no_grad():
        for v in av.capture.split.train_views:
            cam = SplatCamera.from_camera(av.capture.cameras[v].pinhole())
            rgb, alpha = av.model.render_image(av.model.posed_gaussians(state), 0, cam, bg)
            out.append(PoseView(camera=cam, target=rgb, mask=(alpha > 0.5).float()))
    return out


def _shifted(project):
    """(avatar, true conditioning, background, views rendered at it, the root shift, the conditioning shifted)."""
    av, cond = _frame(project)
    bg = torch.tensor(av.background, dtype=torch.float32)
    views = _views(av, cond, bg)
    shift = torch.tensor([0.03, -0.02, 0.01])
    M = cond.joint_transforms.clone()
    M[..., :3, 3] += shift  # every joint moved: the root translation is off by `shift`
    return av, cond, bg, views, shift, replace(cond, joint_transforms=M)


def test_a_known_root_shift_is_recovered_and_the_avatar_is_left_as_it_was(toy_gaussian_project):
    from avatarctl.fit.frame_pose import FramePoseConfig, refine_frame_pose, refined_state

    av, cond, bg, views, shift, off = _shifted(toy_gaussian_project)
    before = {k: v.clone() for k, v in av.model.state_dict().items()}
    pose = refine_frame_pose(av.model, av.template, off, views, bg, "zero", FramePoseConfig(steps=60))
    assert pose.loss_end < 0.25 * pose.loss_start
    assert np.abs(pose.tau + shift.numpy()).max() < 0.01, pose.tau  # back within 1 cm of where it was rendered
    assert pose.joint_transforms.shape == cond.joint_transforms.shape
    assert all(torch.equal(before[k], v) for k, v in av.model.state_dict().items())
    assert all(p.grad is None for p in av.model.parameters())
    again = refine_frame_pose(av.model, av.template, off, views, bg, "zero", FramePoseConfig(steps=60))
    assert np.array_equal(again.tau, pose.tau)  # deterministic
    state = refined_state(av.model, off, pose, "zero")
    true = av.model.node_state(cond, mode="zero")
    assert (state.centers - true.centers).norm(dim=-1).median() < 0.01


def test_the_masks_alone_move_a_shifted_pose_back_without_the_colours(toy_gaussian_project):
    """`target="masks"`: the same shift recovered from the silhouette; the targets' colours are not read (noise
    in their place changes nothing)."""
    from avatarctl.fit.frame_pose import FramePoseConfig, refine_frame_pose

    av, cond, bg, views, shift, off = _shifted(toy_gaussian_project)
    cfg = FramePoseConfig(steps=60, target="masks")
    pose = refine_frame_pose(av.model, av.template, off, views, bg, "zero", cfg)
    assert pose.loss_end < pose.loss_start  # (a soft alpha against a binary mask: not to zero)
    assert np.abs(pose.tau + shift.numpy()).max() < 0.015, pose.tau
    noise = [replace(v, target=torch.rand_like(v.target)) for v in views]
    again = refine_frame_pose(av.model, av.template, off, noise, bg, "zero", cfg)
    assert np.array_equal(again.tau, pose.tau) and again.loss_end == pose.loss_end
    with pytest.raises(ValueError, match="target"):
        FramePoseConfig(target="colours")


def test_a_pose_that_is_already_right_is_never_made_worse(toy_gaussian_project):
    """Started at the pose the targets were rendered with, the refinement returns a loss no higher than the start's:
    improved, or the estimated pose kept exactly (zero corrections)."""
    from avatarctl.fit.frame_pose import FramePoseConfig, refine_frame_pose

    av, cond = _frame(toy_gaussian_project)
    bg = torch.tensor(av.background, dtype=torch.float32)
    pose = refine_frame_pose(av.model, av.template, cond, _views(av, cond, bg), bg, "zero",
                             FramePoseConfig(steps=6, lr=0.05))  # steps far too large for a pose already right
    assert pose.loss_end <= pose.loss_start
    if pose.loss_end == pose.loss_start:
        assert not pose.tau.any() and not pose.delta.any()
        assert torch.equal(pose.joint_transforms, cond.joint_transforms)


def test_a_start_from_a_neighbour_is_kept_only_where_it_is_better(toy_gaussian_project):
    """`start_from`: Adam starts at the given corrections; the frame keeps the best of the estimated pose, that start
    and the end. Started at the true correction with steps far too large, it keeps the start; started at a wrong
    one, it never ends worse than the estimated pose."""
    from avatarctl.fit.frame_pose import FramePoseConfig, refine_frame_pose

    av, cond, bg, views, shift, off = _shifted(toy_gaussian_project)
    J = cond.joint_transforms.shape[1]
    right = (np.zeros((J, 3), np.float32), -shift.numpy())
    cfg = FramePoseConfig(steps=4, lr=0.2, target="masks")  # steps far too large: Adam wanders off
    kept = refine_frame_pose(av.model, av.template, off, views, bg, "zero", cfg, start_from=right)
    assert kept.loss_end < kept.loss_start and np.abs(kept.tau + shift.numpy()).max() < 0.005, kept.tau  # the start
    wrong = (np.zeros((J, 3), np.float32), 3 * shift.numpy())
    safe = refine_frame_pose(av.model, av.template, off, views, bg, "zero", cfg, start_from=wrong)
    assert safe.loss_end <= safe.loss_start


def test_the_coarse_camera_sees_the_downsampled_image():
    """`_downsampled`: a point projected by the 2x coarser camera lands on the coarse pixel that averages the fine
    pixels it falls on (pixel centres at integers)."""
    from avatarctl.fit.frame_pose import PoseView, _downsampled
    from avatarctl.splat import SplatCamera

    K = torch.tensor([[50.0, 0, 15.5], [0, 50.0, 11.5], [0, 0, 1]])
    cam = SplatCamera(K=K, R=torch.eye(3), T=torch.zeros(3), width=32, height=24)
    view = PoseView(camera=cam, target=torch.rand(24, 32, 3), mask=torch.ones(24, 32))
    coarse = _downsampled(view, 2)
    assert (coarse.camera.width, coarse.camera.height) == (16, 12) and coarse.target.shape == (12, 16, 3)
    x = torch.tensor([0.1, -0.05, 1.0])
    u_fine = (K @ x)[:2] / x[2]
    u_coarse = (coarse.camera.K @ x)[:2] / x[2]
    assert torch.allclose(u_coarse, (u_fine - 0.5) / 2, atol=1e-5)  # fine pixels 2i, 2i+1 -> coarse pixel i
    assert torch.allclose(coarse.target[3, 5], view.target[6:8, 10:12].mean((0, 1)))


def test_refusals(toy_gaussian_project, toy_fitted_project):
    from avatarctl.errors import InputError
    from avatarctl.fit.frame_pose import refine_frame_pose
    from avatarctl.stages import evaluate
    from avatarctl.stages.evaluate import EvalConfig

    av, cond = _frame(toy_gaussian_project)
    bg = torch.zeros(3)
    with pytest.raises(ValueError, match="deterministic"):
        refine_frame_pose(av.model, av.template, cond, _views(av, cond, bg), bg, "sample")
    with pytest.raises(InputError, match="deterministic latent"):
        EvalConfig(refine_pose=5, latent="sample")
    with pytest.raises(InputError, match=">= 0 steps"):
        EvalConfig(refine_pose=-1)
    with pytest.raises(InputError, match="refine-pose-from"):
        EvalConfig(refine_pose=5, refine_pose_from="colours")
    with pytest.raises(InputError, match="Gaussian local fields"):  # the MLP toy avatar
        evaluate.run(toy_fitted_project, EvalConfig(split="novel_pose", name="refuse", device="cpu", refine_pose=2))
    assert not (toy_fitted_project / "eval" / "refuse").exists()  # nothing half-written


def test_eval_reports_the_refined_figure_apart(toy_gaussian_project):
    from typer.testing import CliRunner

    from avatarctl.cli.app import app
    from avatarctl.evaluate.report import EvalMetrics
    from avatarctl.stages import evaluate
    from avatarctl.stages.evaluate import EvalConfig

    plain = evaluate.run(toy_gaussian_project, EvalConfig(split="novel_pose", name="plain", device="cpu")).metrics
    assert plain.refined_pose is None
    res = CliRunner().invoke(app, ["eval", str(toy_gaussian_project), "--split", "novel_pose", "--name", "refined",
                                   "--refine-pose", "12", "--device", "cpu"], env={"COLUMNS": "250"})
    assert res.exit_code == 0, res.output
    out = toy_gaussian_project / "eval" / "refined"
    m = EvalMetrics.from_json(json.loads((out / "metrics.json").read_text()))
    assert m.psnr == pytest.approx(plain.psnr, abs=1e-9)  # the headline is the plain figure
    rp = m.refined_pose
    assert rp["steps"] == 12 and rp["images"] == m.images and "frozen" in rp["protocol"]
    assert rp["plain_psnr"] == pytest.approx(plain.psnr, abs=1e-9) and rp["psnr"] != rp["plain_psnr"]
    assert rp["seconds"] > 0 and rp["shift_cm"] >= 0
    rows = (out / "per_frame.csv").read_text().splitlines()
    assert "refined_psnr" in rows[0] and all(r.split(",")[8] for r in rows[1:])
    assert (out / "sheet_refined.png").is_file() and (out / "sheet.png").is_file()
    assert any("refined pose" in line and "frozen" in line for line in res.output.splitlines())
    assert rp["target"] == "images"
    res = CliRunner().invoke(app, ["eval", str(toy_gaussian_project), "--split", "novel_pose", "--name", "masks",
                                   "--refine-pose", "12", "--refine-pose-from", "masks", "--device", "cpu"],
                             env={"COLUMNS": "250"})
    assert res.exit_code == 0, res.output
    m = EvalMetrics.from_json(json.loads((toy_gaussian_project / "eval" / "masks" / "metrics.json").read_text()))
    rp = m.refined_pose
    assert rp["target"] == "masks" and "masks" in rp["protocol"] and m.psnr == pytest.approx(plain.psnr, abs=1e-9)
    assert rp["plain_psnr"] == pytest.approx(plain.psnr, abs=1e-9)
    assert any("refined against its masks" in line for line in res.output.splitlines())
