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
    assert "pose" in res.losses and "pose_accel" in res.losses  # the smoothness term is on by default
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
    (cap / "capture.json").write_text(json.dumps({"generator": "synth-1", "config": {"fit_noise_deg": 0.0}}))
    assert decided(FitRequest()) is False  # synth with exact fits
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


def _walk(frames: int) -> torch.Tensor:
    """[F, 3, 4, 4] the chain translating at constant velocity (zero acceleration), joints unrotated."""
    M = torch.eye(4).repeat(frames, 3, 1, 1)
    M[:, :, 0, 3] = 0.05 * torch.arange(frames, dtype=torch.float32)[:, None]
    return M


def test_acceleration_is_zero_for_steady_motion_and_skips_gaps_in_the_frames():
    ref = PoseRefinement(num_frames=6, parents=PARENTS)
    ref.set_centres(CENTRES.float())
    ref.set_sequence(_walk(6), [0, 1, 2, 3, 5, 7], fps=1.0)
    assert ref.triples.tolist() == [[0, 1, 2], [1, 2, 3], [3, 4, 5]]  # (2, 3, 5) spans unequal gaps
    assert float(ref.acceleration().detach()) < 1e-10
    with torch.no_grad():
        ref.tau[2] = torch.tensor([0.0, 0.02, 0.0])  # a 2 cm jolt of the root at slot 2 moves all 3 joints
    # slot 2 is the middle of (1, 2, 3) (-2 x 2 cm) and an end of (0, 1, 2) (1 x 2 cm): 3 joints x (4 + 1) x 4e-4 / 3
    assert float(ref.acceleration().detach()) == pytest.approx(3 * 5 * 4e-4 / 3, rel=1e-5)
    # in m/s^2: the same jolt between frames twice as dense costs 2^4 = 16 times as much
    ref.set_sequence(_walk(6), [0, 1, 2, 3, 5, 7], fps=2.0)
    assert float(ref.acceleration().detach()) == pytest.approx(16 * 3 * 5 * 4e-4 / 3, rel=1e-5)
    with pytest.raises(ValueError, match="training frames"):
        ref.set_sequence(_walk(5), [0, 1, 2, 3, 4], fps=1.0)
    with pytest.raises(ValueError, match="frame rate"):
        ref.set_sequence(_walk(6), [0, 1, 2, 3, 4, 5], fps=0.0)


def test_the_acceleration_term_alone_takes_the_jitter_out_of_a_jittered_sequence():
    g = torch.Generator().manual_seed(0)
    true = _walk(20)
    jittered = true.clone()
    jittered[:, :, :3, 3] += 0.02 * torch.randn(20, 1, 3, generator=g)  # per-frame root jitter, 2 cm
    ref = PoseRefinement(num_frames=20, parents=PARENTS)
    ref.set_centres(CENTRES.float())
    ref.set_sequence(jittered, list(range(20)), fps=1.0)
    opt = torch.optim.Adam(ref.parameters(), lr=2e-3)
    ids = torch.arange(20)

    def root_error() -> float:
        with torch.no_grad():
            return float((ref(jittered, ids)[:, 0, :3, 3] - true[:, 0, :3, 3]).norm(dim=-1).mean())

    before = root_error()
    for _ in range(300):
        opt.zero_grad()
        ref.acceleration().backward()
        opt.step()
    # frames next to each other now agree: the jitter is mostly gone (a steady walk is what is left to fit)
    assert root_error() < 0.5 * before


def test_acceleration_on_the_refined_sub_tree_equals_the_full_composition():
    """The term composes only the refined joints and their ancestors: the same value as composing the whole tree."""
    parents = (-1, 0, 1, 2, 1, 4, 0)  # a root, a spine with two branches, one leaf under the root
    active = torch.tensor([True, True, True, False, True, False, False])  # closed under ancestors, like subtree_share
    g = torch.Generator().manual_seed(3)
    T = 7
    ref = PoseRefinement(num_frames=T, parents=parents, active=active)
    ref.set_centres(0.2 * torch.randn(7, 3, generator=g))
    base = _walk(T).repeat(1, 3, 1, 1)[:, :7].clone()
    base[:, :, :3, 3] += 0.05 * torch.randn(T, 7, 3, generator=g)
    ref.set_sequence(base, list(range(T)), fps=1.0)
    with torch.no_grad():
        ref.delta.copy_(0.2 * torch.randn(T, 7, 3, generator=g))
        ref.tau.copy_(0.02 * torch.randn(T, 3, generator=g))
    assert ref.sub_joints.tolist() == [0, 1, 2, 4]
    M = ref(base, torch.arange(T))  # the full tree
    x = (M[..., :3, :3] @ ref.centres[None, :, :, None])[..., 0] + M[..., :3, 3]
    a = x[:-2] - 2 * x[1:-1] + x[2:]
    full = (a[:, active] ** 2).sum((-1, -2)).mean()
    assert float(ref.acceleration().detach()) == pytest.approx(float(full.detach()), rel=1e-5)
