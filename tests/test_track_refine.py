"""The tracked garment nodes' per-frame corrections (`model.track_refine`, model/track_refine.py)."""

import math

import pytest
import torch


def _model_with_tracks(**refine):
    from fixtures.toy_capture import toy_motion

    from avatarctl.body.toy import ToyBody
    from avatarctl.model import ModelConfig
    from avatarctl.model.avatar import FrameConditioning, SlrfAvatar

    body = ToyBody()
    motion = toy_motion(3)
    template = body.template(motion)
    cfg = ModelConfig(num_nodes=16, track_free=0.0, track_refine={"enabled": True, **refine})
    model = SlrfAvatar(cfg, template, num_frames=3).eval()
    posed = body.pose(motion)
    J = posed.joint_transforms.shape[1]
    cond = FrameConditioning(posed.joint_transforms.float(), torch.zeros(3, J, 3), torch.linspace(0, 1, 3),
                             torch.tensor([0, 1, -1]))
    paper = model.node_state(cond, mode="zero")  # no tracks yet: Eq. 1-3
    nodes = torch.tensor([3, 5])
    rot = torch.eye(3).expand(3, 2, 3, 3).clone()
    centre = torch.arange(18, dtype=torch.float32).reshape(3, 2, 3) / 10
    model.set_tracks(nodes, rot, centre)
    return model, cond, nodes, centre, paper, template


def test_the_corrections_start_as_the_tracks_and_move_the_tracked_nodes_of_training_frames_only():
    from avatarctl.body.lbs import axis_angle_to_matrix

    model, cond, nodes, centre, paper, _ = _model_with_tracks()
    r = model.track_refine
    assert r.translation.shape == r.rotation.shape == (3, 16, 3)  # [frames, nodes, 3], zero: the tracks as they are
    start = model.node_state(cond, mode="zero")
    torch.testing.assert_close(start.centers[:2, nodes], centre[:2])
    assert float(start.refine_penalty.detach()) == 0.0
    with torch.no_grad():
        r.translation[1, 5] = torch.tensor([0.01, 0.0, 0.0])
        r.rotation[1, 5] = torch.tensor([0.0, 0.0, 0.5])
        r.translation[2, 3] = torch.tensor([0.3, 0.3, 0.3])  # frame index 2 is not in the batch's training frames
    moved = model.node_state(cond, mode="zero")
    torch.testing.assert_close(moved.centers[1, 5], centre[1, 1] + torch.tensor([0.01, 0.0, 0.0]))
    torch.testing.assert_close(moved.transforms[1, 5, :3, :3], axis_angle_to_matrix(torch.tensor([0.0, 0.0, 0.5])))
    torch.testing.assert_close(moved.centers[0], start.centers[0])  # frame 0 has no correction
    torch.testing.assert_close(moved.centers[2], start.centers[2])  # a novel pose (id -1): the paper's placement
    other = torch.tensor([i for i in range(16) if i not in (3, 5)])
    torch.testing.assert_close(moved.centers[:, other], start.centers[:, other])
    # L_track pulls Delta n (Eq. 3's centres) to the corrected centres, not to the raw tracks
    torch.testing.assert_close(moved.track_penalty,
                               ((paper.centers[:2, nodes] - moved.centers[:2, nodes]) ** 2).sum((-2, -1)).mean())
    assert not torch.isclose(moved.track_penalty, start.track_penalty)


def test_the_priors_weigh_size_on_the_batch_and_change_between_consecutive_frames():
    model, cond, nodes, *_ = _model_with_tracks(lambda_size=100.0, lambda_smooth=2000.0, rotation_m=0.05)
    r = model.track_refine
    with torch.no_grad():
        r.translation[1, 5] = torch.tensor([0.02, 0.0, 0.0])  # 2 cm on frame 1
        r.rotation[0, 3] = torch.tensor([0.1, 0.0, 0.0])  # 0.1 rad on frame 0
        r.translation[2, 8] = torch.tensor([9.0, 0.0, 0.0])  # an untracked node: never weighed
    size = (0.02 ** 2 + 0.05 ** 2 * 0.1 ** 2) / 2  # mean over the batch's two training frames (0, 1)
    # frame pairs (0, 1), (1, 2): 0.1 rad and 2 cm change at (0, 1); 2 cm at (1, 2)
    smooth = ((0.05 ** 2 * 0.1 ** 2 + 0.02 ** 2) + 0.02 ** 2) / 2
    state = model.node_state(cond, mode="zero")
    assert math.isclose(float(state.refine_penalty.detach()), 100.0 * size + 2000.0 * smooth, rel_tol=1e-5)
    terms = model._with_regularisers(torch.ones(()), torch.ones(()), state)
    assert "refine" in terms.keys()
    state.refine_penalty.backward()
    assert r.translation.grad[2, 5].abs().sum() > 0  # frame 2 is not in the batch: only its smoothness pulls it
    assert r.translation.grad[:, 8].abs().sum() == 0
    model2, cond2, *_ = _model_with_tracks(lambda_smooth=0.0)
    with torch.no_grad():
        model2.track_refine.translation[2, 5] = 1.0
    assert float(model2.node_state(cond2, mode="zero").refine_penalty.detach()) == 0.0  # frame 2 not in the batch


def test_the_corrections_are_saved_with_the_weights_and_learn_at_their_own_rate_after_their_start():
    from avatarctl.fit.config import FitConfig
    from avatarctl.fit.schedule import make_optimizer, make_scheduler, param_groups
    from avatarctl.model.avatar import SlrfAvatar

    model, cond, nodes, _, _, template = _model_with_tracks(start=2, lr=1e-3, lr_rotation=3e-3)
    with torch.no_grad():
        model.track_refine.translation[0, 3] = 0.5
    again = SlrfAvatar(model.cfg, template, num_frames=3)
    again.load_state_dict(model.state_dict())
    torch.testing.assert_close(again.node_state(cond, mode="zero").centers, model.node_state(cond, mode="zero").centers)
    cfg = FitConfig(model=model.cfg, lr_decay_factor=0.5, lr_decay_every=4)
    opt = make_optimizer(cfg, param_groups(cfg, model))
    sched = make_scheduler(cfg, opt)
    track = [g for g in opt.param_groups if g.get("name") == "track"]
    assert [g["params"][0] is p for g, p in zip(track, (model.track_refine.translation,
                                                         model.track_refine.rotation))] == [True, True]
    assert [g["lr"] for g in track] == [0.0, 0.0]  # frozen before step 2
    for _ in range(2):
        opt.step()
        sched.step()
    assert [g["lr"] for g in track] == pytest.approx([1e-3 * 0.5 ** 0.5, 3e-3 * 0.5 ** 0.5])
    assert opt.param_groups[0]["lr"] == pytest.approx(cfg.lr * 0.5 ** 0.5)


def test_auto_is_decided_with_the_tracked_garment_and_checked():
    from avatarctl.fit.config import preset
    from avatarctl.model.config import TrackRefineConfig

    cpu = preset("cpu").model
    assert cpu.track_refine.enabled == "auto" and not cpu.track_refine.on  # undecided: off
    assert cpu.for_tracked_garment().track_refine.on
    assert preset("paper").model.track_refine.enabled is False and preset("cpu-mlp").model.track_refine.enabled is False
    for bad in ({"enabled": "yes"}, {"lambda_size": -1.0}, {"lr": 0.0}, {"start": -1}):
        with pytest.raises(ValueError, match="TrackRefineConfig"):
            TrackRefineConfig(**bad)


@pytest.mark.gpu
def test_the_corrections_on_cuda_match_the_cpu():
    """The same corrected placement, priors and gradients on a CUDA device as on the CPU (pure torch both ways)."""
    model, cond, *_ = _model_with_tracks()
    with torch.no_grad():
        model.track_refine.translation[:, 3] = torch.tensor([0.01, -0.02, 0.005])
        model.track_refine.rotation[1, 5] = torch.tensor([0.1, 0.0, -0.2])
    results = []
    for device in ("cpu", "cuda"):
        m = model.to(device)
        m.zero_grad()
        state = m.node_state(cond.to(device), mode="zero")
        (state.centers.sum() + state.refine_penalty + state.track_penalty).backward()
        results.append([t.detach().cpu() for t in (state.centers, state.transforms, state.refine_penalty,
                                                    state.track_penalty, m.track_refine.translation.grad,
                                                    m.track_refine.rotation.grad)])
    for cpu, cuda in zip(*results):
        torch.testing.assert_close(cuda, cpu, rtol=1e-5, atol=1e-6)
