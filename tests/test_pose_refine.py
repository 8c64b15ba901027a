"""Per-frame pose refinement (model/pose_refine.py), joint centres (body/joints.py), perturbed fits (body/perturb.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from avatarctl.body.joints import joint_centres, posed_joints
from avatarctl.body.lbs import axis_angle_to_matrix
from avatarctl.model.pose_refine import PoseRefinement

CENTRES = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 0.2], [0.0, 0.1, 0.4]], dtype=torch.float64)
PARENTS = (-1, 0, 1)


def _about(R: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """[..., 3, 3] rotation about the point c [3] as [..., 4, 4]."""
    M = torch.zeros(R.shape[:-2] + (4, 4), dtype=R.dtype)
    M[..., :3, :3] = R
    M[..., :3, 3] = c - (R @ c[:, None])[..., 0]
    M[..., 3, 3] = 1
    return M


def _chain(frames: int, seed: int = 0) -> torch.Tensor:
    """[F, 3, 4, 4] transforms of a 3-joint chain pivoting about CENTRES (root: a rigid motion)."""
    g = torch.Generator().manual_seed(seed)
    aa = 0.6 * torch.randn(frames, 3, 3, generator=g, dtype=torch.float64)
    R = axis_angle_to_matrix(aa)
    root = _about(R[:, 0], CENTRES[0])
    root[:, :3, 3] += torch.randn(frames, 3, generator=g, dtype=torch.float64)
    M1 = root @ _about(R[:, 1], CENTRES[1])
    M2 = M1 @ _about(R[:, 2], CENTRES[2])
    return torch.stack([root, M1, M2], 1)


def test_joint_centres_are_recovered_from_transforms_alone():
    M = _chain(12)
    c = joint_centres(M, PARENTS, fallback=torch.zeros(3, 3, dtype=torch.float64))
    assert torch.allclose(c[1:], CENTRES[1:], atol=1e-3)
    x = posed_joints(M, c)
    # a joint centre is where its own transform and its parent's agree
    assert torch.allclose(posed_joints(M[:, 0:1], c[1:2])[:, 0], x[:, 1], atol=1e-3)


def test_refinement_is_identity_at_zero_and_rotates_the_subtree_about_the_joint():
    M = _chain(4).float()
    ref = PoseRefinement(num_frames=4, parents=PARENTS)
    ref.set_centres(CENTRES.float())
    ids = torch.tensor([0, 1, 2, -1])
    assert torch.allclose(ref(M, ids), M, atol=1e-6)
    with torch.no_grad():
        ref.delta[1, 1] = torch.tensor([0.0, 0.0, 0.3])  # frame 1: rotate joint 1
        ref.delta[3, 1] = torch.tensor([0.3, 0.0, 0.0])  # frame 3 is refined but fed as a novel frame below
        ref.tau[1] = torch.tensor([0.01, 0.0, 0.0])
    out = ref(M, ids)
    assert torch.equal(out[3], M[3]) and torch.allclose(out[0], M[0], atol=1e-6)
    x_old, x_new = posed_joints(M[1], CENTRES.float()), posed_joints(out[1], CENTRES.float())
    assert torch.allclose(x_new[0], x_old[0] + torch.tensor([0.01, 0, 0]), atol=1e-5)  # root: translated only
    assert torch.allclose(x_new[1], x_old[1] + torch.tensor([0.01, 0, 0]), atol=1e-5)  # the pivot stays put
    # the child turned by 0.3 rad about the pivot (world z), then moved with the root
    R = axis_angle_to_matrix(torch.tensor([0.0, 0.0, 0.3]))
    want = (R @ (x_old[2] - x_old[1])) + x_old[1] + torch.tensor([0.01, 0, 0])
    assert torch.allclose(x_new[2], want, atol=1e-5)


def test_refinement_gradients_reach_the_corrections_of_the_batch_frames_only():
    M = _chain(3).float()
    ref = PoseRefinement(num_frames=5, parents=PARENTS)
    ref.set_centres(CENTRES.float())
    out = ref(M, torch.tensor([0, 2, -1]))
    (out[..., :3, 3].sum() + ref.penalty(torch.tensor([0, 2, -1]))).backward()
    g = ref.delta.grad.abs().sum((-1, -2))
    assert g[0] > 0 and g[2] > 0 and g[1] == 0 and g[3] == 0 and g[4] == 0
    assert ref.penalty(torch.tensor([-1])) == 0


@pytest.mark.parametrize("body_model", ["toy", "smpl"])
def test_perturb_motion_adds_the_stated_noise_and_keeps_the_input(body_model):
    from avatarctl.body.motion import BodyMotion
    from avatarctl.body.perturb import perturb_motion

    F = 400
    J = 1 if body_model == "toy" else 23
    m = BodyMotion(body_model=body_model, frame_index=np.arange(F), global_orient=np.zeros((F, 3)),
                   body_pose=np.zeros((F, 3 * J)), transl=np.zeros((F, 3)))
    p = perturb_motion(m, rot_deg=2.0, transl_cm=1.0, seed=0)
    angles = np.linalg.norm(p.body_pose.reshape(F, J, 3), axis=-1)
    assert np.rad2deg(np.sqrt((angles ** 2).mean())) == pytest.approx(2.0, rel=0.1)
    assert 100 * p.transl.std() == pytest.approx(1.0, rel=0.1)
    assert not m.body_pose.any() and not m.transl.any()  # the input is untouched
    assert np.array_equal(perturb_motion(m, 2.0, 1.0, seed=0).body_pose, p.body_pose)


def test_drifting_fit_noise_has_the_stated_size_and_neighbouring_frames_agree():
    from avatarctl.body.motion import BodyMotion
    from avatarctl.body.perturb import perturb_motion

    F, J = 2000, 23
    m = BodyMotion(body_model="smpl", frame_index=np.arange(F), global_orient=np.zeros((F, 3)),
                   body_pose=np.zeros((F, 3 * J)), transl=np.zeros((F, 3)))
    for corr in (0.0, 5.0):
        p = perturb_motion(m, rot_deg=2.0, transl_cm=1.0, seed=1, corr_frames=corr)
        aa = p.body_pose.reshape(F, J, 3)
        assert np.rad2deg(np.sqrt((np.linalg.norm(aa, axis=-1) ** 2).mean())) == pytest.approx(2.0, rel=0.1)
        assert 100 * np.sqrt((p.transl ** 2).mean()) == pytest.approx(1.0, rel=0.15)
        # frame-to-frame change relative to the noise itself: ~sqrt(2) for white noise, small when it drifts
        step = np.sqrt(((aa[1:] - aa[:-1]) ** 2).mean() / (aa ** 2).mean())
        assert (step > 1.3) if corr == 0 else (step < 0.25)
    with pytest.raises(ValueError):
        perturb_motion(m, 2.0, 1.0, corr_frames=-1.0)


def test_fit_with_pose_refinement_on_the_toy_chain(tmp_path):
    from fixtures.toy_capture import make_toy_capture

    from avatarctl.fit.checkpoint import load_avatar
    from avatarctl.project import Project
    from avatarctl.stages import fit, ingest
    from avatarctl.stages.fit import FitRequest
    from avatarctl.stages.ingest import IngestConfig

    cap, proj = make_toy_capture(tmp_path / "cap"), tmp_path / "proj"
    ingest.run(proj, IngestConfig(capture=cap, project=proj))
    res = fit.run(proj, FitRequest(preset="micro", iters=6, device="cpu",
                                   overrides=("model.pose_refine.enabled=true", "val_every=0", "log_every=2"),
                                   model_settings={"pose_refine": {"lr": 0.01}}),
                  handle_sigint=False)
    assert "pose" in res.losses
    r = res.refinement  # the toy body cannot invert its transforms: a summary, no motion file
    assert r is not None and r.frames == 3 and r.mean_rotation_deg > 0 and r.path is None  # 3 training frames
    assert not (proj / "fit" / "refined_fits.npz").exists()
    av = load_avatar(Project.open(proj), device="cpu")
    ref = av.model.pose_refine
    assert ref is not None and ref.delta.abs().max() > 0, "the corrections were trained and saved"
    assert torch.allclose(ref.centres[1], torch.zeros(3), atol=1e-2)  # the toy's joints pivot at the centre
    one = av.capture.motion.select([0])
    train = av.conditioning(one, frames_are_training=True)
    with torch.no_grad():
        refined = av.model.node_state(train, mode="mean").centers
        av.model.pose_refine = None
        plain = av.model.node_state(train, mode="mean").centers
    assert not torch.allclose(refined, plain), "renders of training frames use the refined pose"


def test_pose_refinement_is_on_by_default_unless_the_fits_are_ground_truth(tmp_path):
    """`model.pose_refine.enabled = "auto"` (cpu, micro): decided from the capture at fit start, saved decided."""
    import json

    from fixtures.toy_capture import make_toy_capture

    from avatarctl.fit.config import FitConfig
    from avatarctl.fit.loop import decide_auto
    from avatarctl.project import Project
    from avatarctl.stages import fit, ingest
    from avatarctl.stages.fit import FitRequest, fit_config
    from avatarctl.stages.ingest import IngestConfig

    cap, proj = make_toy_capture(tmp_path / "cap"), tmp_path / "proj"
    ingest.run(proj, IngestConfig(capture=cap, project=proj))
    p = Project.open(proj)

    def decided(req: FitRequest) -> bool | str:
        return decide_auto(fit_config(p, req), p).model.pose_refine.enabled

    assert fit_config(p, FitRequest()).model.pose_refine.enabled == "auto"  # the config holds the rule
    assert decided(FitRequest()) is True  # a capture without ground-truth fits
    assert decided(FitRequest(preset="paper")) is False
    assert decided(FitRequest(overrides=("model.pose_refine=false",))) is False  # the flat key of old configs
    assert decided(FitRequest(preset="paper", overrides=("model.pose_refine.enabled=auto",))) is True
    border = decide_auto(fit_config(p, FitRequest()), p).model.gaussians.mask_border_px
    assert border == 1  # the same rule for the masks (GaussianConfig.mask_border_px): a capture's own masks
    (cap / "capture.json").write_text(json.dumps({"generator": "synth-1", "config": {"fit_noise_deg": 0.0}}))
    assert decided(FitRequest()) is False  # synth with exact fits
    assert decide_auto(fit_config(p, FitRequest()), p).model.gaussians.mask_border_px == 0  # and its true masks
    (cap / "capture.json").write_text(json.dumps({"generator": "synth-1", "config": {"fit_noise_deg": 2.0}}))
    assert decided(FitRequest()) is True
    res = fit.run(proj, FitRequest(preset="micro", iters=1, device="cpu", overrides=("val_every=0",)),
                  handle_sigint=False)
    saved = FitConfig.from_json(json.loads(p.paths.fit_config.read_text()))
    assert saved.model.pose_refine.enabled is True and res.config == saved  # the decision, saved


def test_pose_corrections_wait_for_pose_refine_start():
    from fixtures.toy_model import make, small_cfg

    from avatarctl.fit.config import FitConfig
    from avatarctl.fit.schedule import make_optimizer, make_scheduler, param_groups

    model = make(small_cfg(pose_refine={"enabled": True}))
    cfg = FitConfig(model=small_cfg(pose_refine={"enabled": True, "start": 3}))
    opt = make_optimizer(cfg, param_groups(cfg, model))
    sched = make_scheduler(cfg, opt)
    pose_lrs, rest_lrs = [], []
    for _ in range(5):
        pose_lrs.append(opt.param_groups[-1]["lr"])
        rest_lrs.append(opt.param_groups[0]["lr"])
        opt.step()
        sched.step()
    assert pose_lrs[:3] == [0.0] * 3 and pose_lrs[3] == pytest.approx(cfg.model.pose_refine.lr, rel=1e-3)
    assert all(lr > 0 for lr in rest_lrs)


def test_a_config_saved_with_the_removed_smoothness_term_reads():
    """Avatars fitted before 2026-11-29 saved `pose_refine.lambda_accel` (schema 2) or `lambda_pose_accel` (schema 1):
    a training-only weight, dropped on read."""
    from avatarctl.model.config import ModelConfig

    saved = ModelConfig().to_json()
    saved["pose_refine"] = {**saved["pose_refine"], "lambda_accel": 2e-3}
    assert ModelConfig.from_json(saved) == ModelConfig()
    assert ModelConfig.from_json({"schema_version": 1, "lambda_pose_accel": 2e-3, "rec_reduction": "sum"}) \
        == ModelConfig()
