"""fit/garment_track.py: a printed tube turning around a still body, rendered by ray casting into six views; the
tracker follows it, the reference surface (a tube from the masks) finds it, node motions and the model's tracked
placement."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from avatarctl.fit import garment_track as gt
from avatarctl.geometry.cameras import Camera, look_at

SIZE, TURN = 112, 0.06  # image side (pixels); the tube turns by this many radians per frame (1.8 cm at its surface)


def _radius(a: np.ndarray, radius: float, folds: float) -> np.ndarray:
    return radius + folds * np.sin(5 * a)


def _tube(rings: int = 12, segments: int = 60, radius: float = 0.3, height: float = 0.4, folds: float = 0.05
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An open tube around the z axis with `folds` (metres) of 5 folds -> (vertices [V, 3], faces [T, 3], material
    coordinates [V, 2]). The folds' hollows are what a visual hull of a few views cannot carve."""
    a = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    z = np.linspace(-height / 2, height / 2, rings)
    A, Z = np.meshgrid(a, z)
    r = _radius(A, radius, folds)
    V = np.stack([r * np.cos(A), r * np.sin(A), Z], -1).reshape(-1, 3)
    faces = []
    for r in range(rings - 1):
        for s in range(segments):
            i, j = r * segments + s, r * segments + (s + 1) % segments
            faces += [[i, j, i + segments], [j, j + segments, i + segments]]
    return V, np.asarray(faces), np.stack([A, Z], -1).reshape(-1, 2)


def _body() -> tuple[np.ndarray, np.ndarray]:
    """The still 'body': a thin tube on the axis (vertices 2 cm apart, as the off-body rule measures to them)."""
    v, f, _ = _tube(rings=26, segments=24, radius=0.08, height=0.5, folds=0.0)
    return v, f


def _cameras(n: int = 6) -> tuple[Camera, ...]:
    cams = []
    for i in range(n):
        a = 2 * np.pi * (i + 0.3) / n
        R, T = look_at(np.array([2.5 * np.cos(a), 2.5 * np.sin(a), 0.6]), np.zeros(3))
        K = np.array([[160.0, 0, SIZE / 2], [0, 160.0, SIZE / 2], [0, 0, 1]])  # every view sees the carved box
        cams.append(Camera(f"c{i}", K, R, T, SIZE, SIZE))
    return tuple(cams)


def _render(cam: Camera, verts: np.ndarray, faces: np.ndarray, uv: np.ndarray, body: tuple[np.ndarray, np.ndarray]
            ) -> tuple[np.ndarray, np.ndarray]:
    """RGB uint8 [H, W, 3] and mask of the printed tube and the grey body (one ray per pixel, Warp's BVH)."""
    from avatarctl.geometry.raycast import RayCaster

    bv, bf = body
    caster = RayCaster(np.concatenate([verts, bv]), np.concatenate([faces, bf + len(verts)]))
    v, u = np.mgrid[0:cam.height, 0:cam.width]
    xy = (np.stack([u, v], -1).reshape(-1, 2) - cam.K[:2, 2]) / np.diag(cam.K)[:2]
    d = np.concatenate([xy, np.ones((len(xy), 1))], -1) @ cam.R
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    face, t = caster.cast(cam.center, d)
    img = np.zeros((len(d), 3))
    tube = (face >= 0) & (face < len(faces))
    p = cam.center + t[tube, None] * d[tube]
    tri = verts[faces[face[tube]]]  # [n, 3, 3] barycentric coordinates of the hit
    e1, e2, q = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], p - tri[:, 0]
    d11, d12, d22 = (e1 * e1).sum(-1), (e1 * e2).sum(-1), (e2 * e2).sum(-1)
    q1, q2 = (q * e1).sum(-1), (q * e2).sum(-1)
    den = d11 * d22 - d12 ** 2
    b1, b2 = (d22 * q1 - d12 * q2) / den, (d11 * q2 - d12 * q1) / den
    m = np.einsum("nk,nkd->nd", np.stack([1 - b1 - b2, b1, b2], -1), uv[faces[face[tube]]])  # material (a, z)
    img[tube] = 0.5 + 0.4 * np.stack([np.sin(9 * m[:, 0]) * np.sin(31 * m[:, 1]), np.cos(13 * m[:, 0] + 20 * m[:, 1]),
                                      np.sin(7 * m[:, 0] - 25 * m[:, 1])], -1)
    img[face >= len(faces)] = 0.45
    return (img.reshape(cam.height, cam.width, 3) * 255).astype(np.uint8), (face >= 0).reshape(cam.height, cam.width)


def _turned(verts: np.ndarray, angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return verts @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T


def _swung(verts: np.ndarray, angle: float) -> np.ndarray:
    """The tube's rings turned by `angle` at its lower rim, less towards the top (none there): a skirt's swing."""
    share = (verts[:, 2].max() - verts[:, 2]) / np.ptp(verts[:, 2])
    return np.stack([_turned(v[None], angle * w)[0] for v, w in zip(verts, share)])


def _scene(turn: float, swing: bool = False):
    """Three frames of the tube turning by `turn` radians per frame around the still box (`swing`: at its lower rim
    only, less towards the top), in six views."""
    verts, faces, uv = _tube()
    body = _body()
    cams = _cameras()
    frames = [(_swung if swing else _turned)(verts, turn * (f - 1)) for f in range(3)]
    shots = {(c, f): _render(cam, frames[f], faces, uv, body) for c, cam in enumerate(cams) for f in range(3)}
    eye = np.broadcast_to(np.eye(4), (1, 4, 4))
    inp = gt.TrackingInput(frames=(0, 1, 2), cameras=cams, image=lambda c, f: shots[(c, f)][0],
                           mask=lambda c, f: shots[(c, f)][1], body_vertices=np.stack([body[0]] * 3),
                           body_faces=body[1], body_transforms=lambda fi, j: np.repeat(eye, len(j), 0),
                           up=np.tile([0.0, 0.0, 1.0], (3, 1)))
    return inp, verts, faces, frames


@pytest.fixture(scope="module")
def scene():
    return _scene(TURN)


def test_the_tracker_follows_the_turning_print(scene):
    inp, verts, faces, truth = scene
    mesh = gt.GarmentMesh(truth[1], faces, frame=1)
    tracks = gt.track(inp, mesh, ref=1)
    assert tracks.vertices.shape == (3, len(verts), 3)
    np.testing.assert_array_equal(tracks.vertices[1], truth[1])
    for f in (0, 2):
        still = np.linalg.norm(truth[1] - truth[f], axis=-1).mean()  # the skeleton (still) explains none of it
        err = np.linalg.norm(tracks.vertices[f] - truth[f], axis=-1).mean()
        assert still > 0.015
        assert err < 0.3 * still, (f, err, still)
    assert (tracks.seen[[0, 2]] >= 2).mean() > 0.5


def test_the_twist_presolve_turns_each_ring_with_a_swinging_print():
    """Step 2's pre-solve (`_Tracker.twist`) from the still start: each ring turned by its own angle lands near the
    swung tube (0.3 rad at the lower rim, none at the top), and a surface that is no tube is refused its rings."""
    inp, verts, faces, truth = _scene(0.3, swing=True)
    mesh = gt.GarmentMesh(truth[1], faces, frame=1, segments=60)
    tracker = gt._Tracker(inp, mesh, 1, gt.TrackSettings())
    svis = tracker._sample_vis(torch.as_tensor(gt.visibility(inp, 1, truth[1], faces)).float())
    start = tracker.twist(truth[1], torch.as_tensor(truth[1], dtype=torch.float32), svis, 1, 2)
    still = np.linalg.norm(truth[2] - truth[1], axis=-1)
    err = np.linalg.norm(start - truth[2], axis=-1)
    assert err.mean() < 0.1 * still.mean(), (err.mean(), still.mean())
    low = verts[:, 2] < verts[:, 2].min() + 0.1  # the lower rings, which swing the most
    assert err[low].mean() < 0.1 * still[low].mean()
    assert np.allclose(np.linalg.norm(start[:, :2], axis=-1), np.linalg.norm(truth[1][:, :2], axis=-1), atol=1e-5)
    with pytest.raises(AssertionError, match="rings"):
        gt.GarmentMesh(truth[1], faces, frame=1, segments=7)


def test_the_reference_surface_is_a_tube_around_the_garment_from_the_masks(scene):
    inp, *_ = scene
    tube = gt.reference_mesh(inp, 1)
    side = np.abs(tube.vertices[:, 2]) < 0.15  # the garment's height (the tube reaches tube_top above it)
    assert side.sum() > 500 and tube.vertices[:, 2].min() < -0.15 and tube.vertices[:, 2].max() > 0.2
    f = tube.faces
    _, uses = np.unique(np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), 1), axis=0,
                        return_counts=True)
    assert set(uses.tolist()) == {1, 2} and (uses == 1).sum() == 2 * gt.TrackSettings().tube_segments  # one tube: open at its two rims only
    n = gt.vertex_normals(tube.vertices, tube.faces)
    assert (np.einsum("vi,vi->v", n[side, :2], tube.vertices[side, :2]) > 0).mean() > 0.95  # normals outwards

    def off(X: np.ndarray) -> np.ndarray:  # radial distance (metres) to the folded tube
        return np.abs(np.linalg.norm(X[:, :2], axis=-1) - _radius(np.arctan2(X[:, 1], X[:, 0]), 0.3, 0.05))

    assert np.median(off(tube.vertices[side])) < 0.05  # the hull's boundary: outside the folds' hollows
    stereo = gt.refine_reference(inp, tube, 1)
    before, after = off(tube.vertices[side]), off(stereo.vertices[side])
    assert np.median(after) < np.median(before)  # the stereo brings the hull's surface onto the printed tube
    empty = gt.TrackingInput(frames=inp.frames, cameras=inp.cameras, image=inp.image,
                             mask=lambda c, f: np.zeros((SIZE, SIZE), bool), body_vertices=inp.body_vertices,
                             body_faces=inp.body_faces, body_transforms=inp.body_transforms, up=inp.up)
    assert len(gt.reference_mesh(empty, 1).vertices) == 0  # nothing off the body: no garment


def test_node_motions_recover_a_rigid_motion_and_skip_empty_nodes():
    rng = np.random.default_rng(0)
    X = rng.normal(size=(200, 3)) * 0.1
    R = _turned(np.eye(3), 0.4).T  # a rotation about z (rows of the turned identity)
    moved = X @ R.T + np.array([0.1, -0.2, 0.05])
    mesh = gt.GarmentMesh(X, np.zeros((0, 3), dtype=np.int64), frame=0)
    tracks = gt.GarmentTracks(mesh=mesh, frames=(0, 1), vertices=np.stack([X, moved]), seen=np.full((2, 200), 3),
                              loss=np.zeros(2), tracked=np.ones(2, dtype=bool))
    m = gt.node_motions(tracks, 0, np.array([7, 9]), np.array([[0.0, 0.0, 0.0], [5.0, 5.0, 5.0]]), patch=200)
    assert m.nodes.tolist() == [7]  # node 9 owns no surface
    np.testing.assert_allclose(m.rotation[1, 0], R, atol=1e-9)
    np.testing.assert_allclose(m.rotation[0, 0], np.eye(3), atol=1e-9)
    np.testing.assert_allclose(X @ m.rotation[1, 0].T + m.translation[1, 0], moved, atol=1e-9)


def test_placement_holds_the_last_tracked_offset_from_the_skeleton_where_the_tracker_stops():
    rng = np.random.default_rng(1)
    F, M, ref = 7, 3, 3
    A = np.stack([[_turned(np.eye(3), a) for a in rng.uniform(-1, 1, M)] for _ in range(F)])  # [F, M, 3, 3]
    c = rng.normal(size=(F, M, 3))
    R = np.stack([[_turned(np.eye(3), a) for a in rng.uniform(-1, 1, M)] for _ in range(F)])
    t = rng.normal(size=(F, M, 3))
    tracked = np.array([False, True, True, True, True, False, False])  # lost at 0 backwards, at 5 forwards
    rot, cen = gt.placement(R, t, A, c, tracked, ref)
    np.testing.assert_allclose(rot[tracked], R[tracked])
    np.testing.assert_allclose(cen[tracked], t[tracked])
    for f, g in ((0, 1), (5, 4), (6, 4)):  # the offset in the node's skeleton frame is the last tracked one's
        np.testing.assert_allclose(np.swapaxes(A[f], -1, -2) @ rot[f], np.swapaxes(A[g], -1, -2) @ R[g], atol=1e-12)
        np.testing.assert_allclose(np.einsum("mji,mj->mi", A[f], cen[f] - c[f]),
                                   np.einsum("mji,mj->mi", A[g], t[g] - c[g]), atol=1e-12)


def test_the_model_places_tracked_nodes_on_training_frames_only(tmp_path):
    from fixtures.toy_capture import toy_motion

    from avatarctl.body.toy import ToyBody
    from avatarctl.model import ModelConfig
    from avatarctl.model.avatar import FrameConditioning, SlrfAvatar

    body = ToyBody()
    motion = toy_motion(3)
    template = body.template(motion)
    model = SlrfAvatar(ModelConfig(num_nodes=16), template, num_frames=3).eval()  # eval: every frame by its tracks
    posed = body.pose(motion)
    J = posed.joint_transforms.shape[1]
    cond = FrameConditioning(posed.joint_transforms.float(), torch.zeros(3, J, 3), torch.linspace(0, 1, 3),
                             torch.tensor([0, 1, -1]))
    before = model.node_state(cond, mode="zero")
    nodes = torch.tensor([3, 5])
    rot = torch.eye(3).expand(3, 2, 3, 3).clone()
    centre = torch.arange(18, dtype=torch.float32).reshape(3, 2, 3)
    model.set_tracks(nodes, rot, centre)
    after = model.node_state(cond, mode="zero")
    torch.testing.assert_close(after.centers[:2, nodes], centre[:2])  # training frames 0 and 1: the tracks
    assert before.track_penalty is None  # L_track: Eq. 3's centres (with Delta n) against the tracked ones
    torch.testing.assert_close(after.track_penalty, ((before.centers[:2, nodes] - centre[:2]) ** 2).sum((-2, -1)).mean())
    from avatarctl.model.losses import total_loss

    one = torch.ones(())
    terms = total_loss(one, one, one, one, 1.0, 0.0, 0.0, 0.0, mse=one, track=after.track_penalty, lambda_track=2.0)
    assert "track" in terms.keys() and torch.isclose(terms.total, 1 + 2 * after.track_penalty)
    torch.testing.assert_close(after.centers[2], before.centers[2])  # a novel pose: the paper's placement
    other = torch.tensor([i for i in range(16) if i not in (3, 5)])
    torch.testing.assert_close(after.centers[:, other], before.centers[:, other])
    again = SlrfAvatar(ModelConfig(num_nodes=16), template, num_frames=3)
    again.load_state_dict(model.state_dict())  # saved with the weights
    torch.testing.assert_close(again.node_state(cond, mode="zero").centers, after.centers)
    with pytest.raises(ValueError, match="tracks for 3 frames"):
        model.set_tracks(nodes, rot[:2], centre[:2])
    # Delta n pulled elsewhere than the placement (the rescued frames' placement without the rescue)
    offset = torch.zeros(3, 2, 3)
    offset[1] = 0.5
    model.set_tracks(nodes, rot, centre, offset)
    pulled = model.node_state(cond, mode="zero")
    torch.testing.assert_close(pulled.centers, after.centers)  # placed as before
    torch.testing.assert_close(pulled.track_penalty, ((before.centers[:2, nodes] - centre[:2] - offset[:2]) ** 2
                                                      ).sum((-2, -1)).mean())
    old = {k: v for k, v in model.state_dict().items() if k != "track_pull"}  # a fit saved before the pull existed
    again.load_state_dict(old)
    torch.testing.assert_close(again.node_state(cond, mode="zero").track_penalty, after.track_penalty)


def test_in_training_a_share_of_the_frames_keeps_the_paper_placement():
    """`model.track_free`: in a training step each training frame's tracked nodes keep the skeleton + Delta n
    placement with that probability (L_track still over every frame); in eval every training frame is tracked."""
    from fixtures.toy_capture import toy_motion

    from avatarctl.body.toy import ToyBody
    from avatarctl.model import ModelConfig
    from avatarctl.model.avatar import FrameConditioning, SlrfAvatar

    body = ToyBody()
    motion = toy_motion(3)
    template = body.template(motion)
    model = SlrfAvatar(ModelConfig(num_nodes=16, track_free=0.5), template, num_frames=3)
    J = body.pose(motion).joint_transforms.shape[1]
    ids = torch.arange(60) % 3
    cond = FrameConditioning(body.pose(motion).joint_transforms.float()[ids], torch.zeros(60, J, 3),
                             torch.linspace(0, 1, 60), ids)
    bare = model.node_state(cond, mode="zero")
    nodes = torch.tensor([3, 5])
    centre = torch.arange(18, dtype=torch.float32).reshape(3, 2, 3)
    model.set_tracks(nodes, torch.eye(3).expand(3, 2, 3, 3).clone(), centre)
    torch.manual_seed(0)
    trained = model.train().node_state(cond, mode="zero")
    by_tracks = (trained.centers[:, nodes] == centre[ids]).all(-1).all(-1)
    by_paper = torch.isclose(trained.centers[:, nodes], bare.centers[:, nodes]).all(-1).all(-1)
    assert (by_tracks ^ by_paper).all() and 15 <= int(by_paper.sum()) <= 45  # each frame one way, about half each
    torch.testing.assert_close(trained.track_penalty,
                               ((bare.centers[:, nodes] - centre[ids]) ** 2).sum((-2, -1)).mean())
    assert (model.eval().node_state(cond, mode="zero").centers[:, nodes] == centre[ids]).all()
    with pytest.raises(ValueError, match="track_free"):
        ModelConfig(track_free=1.0)


def test_without_the_stop_rule_every_frame_is_tracked(scene, monkeypatch):
    """`track(stop=False)` (benchmarks.garment_tracking --through) goes on where the stop rule ends a direction."""
    inp, verts, faces, truth = scene
    mesh = gt.GarmentMesh(truth[1], faces, frame=1)
    monkeypatch.setattr(gt._Tracker, "explains", lambda self, X, fi: 1.0)  # every frame judged lost
    stopped = gt.track(inp, mesh, ref=1)
    assert stopped.tracked.tolist() == [False, True, False] and not stopped.vertices[[0, 2]].any()
    through = gt.track(inp, mesh, ref=1, stop=False)
    assert through.tracked.all()
    for f in (0, 2):
        assert np.linalg.norm(through.vertices[f] - truth[f], axis=-1).mean() < 0.3 * np.linalg.norm(
            truth[1] - truth[f], axis=-1).mean()


def test_carry_moves_each_point_with_the_surface_nearest_it():
    rng = np.random.default_rng(2)
    Y0 = np.concatenate([rng.normal(size=(50, 3)) * 0.05, rng.normal(size=(50, 3)) * 0.05 + [1.0, 0.0, 0.0]])
    turn = _turned(np.eye(3), 0.5).T
    Y = np.concatenate([Y0[:50] @ turn.T + [0.0, 0.2, 0.0], Y0[50:] + [0.0, 0.0, -0.3]])  # two pieces, two motions
    X = np.array([[0.02, 0.01, 0.0], [1.01, -0.02, 0.03]])
    moved = gt.carry(X, Y0, Y, k=10)
    np.testing.assert_allclose(moved[0], X[0] @ turn.T + [0.0, 0.2, 0.0], atol=1e-9)
    np.testing.assert_allclose(moved[1], X[1] + [0.0, 0.0, -0.3], atol=1e-9)


def test_the_spread_frame_has_the_most_mask_the_body_does_not_explain_and_ignores_one_odd_frame():
    from avatarctl.geometry.silhouette import rasterize_silhouette

    body = _body()
    cams = _cameras(2)
    F = 7
    extra = [4, 6, 10, 14, 12, 8, 40]  # half-widths (pixels) of the garment's patch; frame 6 one odd mask
    sil = [rasterize_silhouette(c, body[0], body[1], supersample=1) for c in cams]

    def mask(c: int, f: int) -> np.ndarray:
        m = sil[c].copy()
        h = SIZE // 2
        m[h + 25:h + 35, h - extra[f]:h + extra[f]] = True  # below the body's silhouette
        return m

    inp = gt.TrackingInput(frames=tuple(range(F)), cameras=cams, mask=mask,
                           image=lambda c, f: np.zeros((SIZE, SIZE, 3), np.uint8),
                           body_vertices=np.stack([body[0]] * F), body_faces=body[1],
                           body_transforms=lambda fi, j: np.repeat(np.eye(4)[None], len(j), 0),
                           up=np.tile([0.0, 0.0, 1.0], (F, 1)))
    assert gt.spread_frame(inp, list(range(F))) == 3  # the widest over three frames, not the lone frame 6
    assert gt.spread_frame(inp, [0, 1, 2]) == 2
    assert gt.spread_frame(inp, [5, 4, 3]) == 3  # frames in either order


def test_rescue_follows_the_frames_the_tracker_lost_and_keeps_the_rest(scene, monkeypatch):
    """Both directions lost at once (the stop rule made to judge every frame lost): the rescue's second surface,
    built from the masks at each lost frame, carries the first one onto the turned print."""
    inp, verts, faces, truth = scene
    mesh = gt.GarmentMesh(truth[1], faces, frame=1)
    with monkeypatch.context() as m:
        m.setattr(gt._Tracker, "explains", lambda self, X, fi: 1.0)
        lost = gt.track(inp, mesh, ref=1)
    assert lost.tracked.tolist() == [False, True, False]
    untouched = gt.rescue(inp, lost, 1)  # fewer lost frames than `rescue_min_frames` on each side
    assert untouched.tracked.tolist() == [False, True, False]
    rescued = gt.rescue(inp, lost, 1, gt.TrackSettings(rescue_min_frames=1))
    assert rescued.tracked.all()
    np.testing.assert_array_equal(rescued.vertices[1], truth[1])
    for f in (0, 2):
        still = np.linalg.norm(truth[1] - truth[f], axis=-1).mean()
        assert np.linalg.norm(rescued.vertices[f] - truth[f], axis=-1).mean() < 0.5 * still, f
        assert (rescued.seen[f] >= 2).mean() > 0.5


@pytest.mark.parametrize("broken", [True, False])
def test_rescue_keeps_the_side_tracked_with_or_without_the_twist_whichever_fits(scene, monkeypatch, broken):
    """The rescue tracks each side's second tube with the twist pre-solve and without (each loses the cloth on some
    captures) and keeps the one whose carried surfaces the reference colours fit best: with either made to throw
    the surface up by 5 cm per frame of its target, the other one is kept and lands on the turned print."""
    inp, verts, faces, truth = scene
    mesh = gt.GarmentMesh(truth[1], faces, frame=1, segments=60)
    with monkeypatch.context() as m:
        m.setattr(gt._Tracker, "explains", lambda self, X, fi: 1.0)
        lost = gt.track(inp, mesh, ref=1)
    step = gt._Tracker.step

    def thrown(self, Xp, Xpp, fa, fb, init=None):
        X, seen, loss = step(self, Xp, Xpp, fa, fb, init)
        return (X + [0.0, 0.0, 0.05 * fb], seen, loss) if bool(self.s.twist) == broken else (X, seen, loss)

    monkeypatch.setattr(gt._Tracker, "step", thrown)
    rescued = gt.rescue(inp, lost, 1, gt.TrackSettings(rescue_min_frames=1))
    assert rescued.tracked.all()
    for f in (0, 2):
        still = np.linalg.norm(truth[1] - truth[f], axis=-1).mean()
        assert np.linalg.norm(rescued.vertices[f] - truth[f], axis=-1).mean() < 0.5 * still, f


@pytest.mark.gpu
def test_the_tracker_on_cuda_follows_the_print_as_on_the_cpu(scene):
    """The same photometric solves on a CUDA device: both follow the turning print, and agree to a few millimetres
    (the solves' reductions differ in order between the devices, so not to the bit)."""
    inp, verts, faces, truth = scene
    mesh = gt.GarmentMesh(truth[1], faces, frame=1)
    cpu = gt.track(inp, mesh, ref=1, device="cpu").vertices
    cuda = gt.track(inp, mesh, ref=1, device="cuda").vertices
    for f in (0, 2):
        err_cpu, err_cuda = (np.linalg.norm(v[f] - truth[f], axis=-1).mean() for v in (cpu, cuda))
        assert err_cuda < err_cpu + 0.001, (f, err_cuda, err_cpu)  # the CPU's: 1.7-1.8 mm of an 18 mm turn
        assert np.linalg.norm(cuda[f] - cpu[f], axis=-1).mean() < 0.003, f
