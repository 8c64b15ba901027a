"""Issue 31: one phone video -> a project. Intrinsics rule, the video reader, the synth `phone` layout, the monocular
body fit (2D keypoints, height prior, ground contact), the similarity alignment it is measured with, MediaPipe's
native log filter, and (with the capture extra) the whole path on a synthetic video."""

from __future__ import annotations

import json
import math
import os
import shutil
import sys

import numpy as np
import pytest
from typer.testing import CliRunner

from avatarctl.cli.app import app


def _write_video(path, frames, fps=10.0, focal_35mm=None):
    import imageio_ffmpeg

    h, w = frames[0].shape[:2]
    params = [] if focal_35mm is None else ["-metadata", f"com.apple.quicktime.camera.focal_length.35mm_equivalent="
                                                         f"{focal_35mm}", "-movflags", "use_metadata_tags"]
    gen = imageio_ffmpeg.write_frames(str(path), (w, h), fps=fps, quality=9, macro_block_size=1,
                                      output_params=params)
    gen.send(None)
    for f in frames:
        gen.send(np.ascontiguousarray(f))
    gen.close()


# ---- intrinsics and the reader (no MediaPipe) ------------------------------------------------------------------
def test_intrinsics_rule_focal_then_fov_then_metadata_then_default():
    from avatarctl.io.monocular import DEFAULT_FOCAL_35MM, diagonal_fov_deg, focal_from_35mm, resolve_intrinsics

    w, h = 1080, 1920
    assert resolve_intrinsics(w, h, 1500.0, 70.0, 26.0).focal_px == 1500.0
    fov = resolve_intrinsics(w, h, None, 70.0, 26.0)
    assert diagonal_fov_deg(fov.focal_px, w, h) == pytest.approx(70.0) and "--fov-deg" in fov.source
    meta = resolve_intrinsics(w, h, None, None, 26.0)
    assert meta.focal_px == pytest.approx(26.0 * math.hypot(w, h) / 43.27) and "metadata" in meta.source
    default = resolve_intrinsics(w, h, None, None, None)
    assert default.focal_px == pytest.approx(focal_from_35mm(DEFAULT_FOCAL_35MM, w, h)) and "default" in default.source
    assert 75 < diagonal_fov_deg(default.focal_px, w, h) < 82  # a phone's main camera


def test_video_reader_one_camera_at_the_origin_with_the_metadata_focal(tmp_path):
    from avatarctl.io.detect import detect_format
    from avatarctl.io.monocular import CAMERA, is_monocular_source, read_monocular, video_focal_35mm

    frames = [np.full((48, 32, 3), 20 * i, np.uint8) for i in range(4)]
    _write_video(tmp_path / "clip.mp4", frames, focal_35mm=28)
    _write_video(tmp_path / "plain.mp4", frames)
    assert video_focal_35mm(tmp_path / "clip.mp4") == 28.0 and video_focal_35mm(tmp_path / "plain.mp4") is None
    src = read_monocular(tmp_path / "clip.mp4")
    cam = src.cameras[0]
    assert src.format == "video" and cam.name == CAMERA and (cam.width, cam.height) == (32, 48)
    assert np.allclose(cam.R, np.eye(3)) and np.allclose(cam.T, 0) and cam.is_pinhole
    assert cam.K[0, 0] == pytest.approx(28 * math.hypot(32, 48) / 43.27) and cam.K[0, 2] == 15.5
    assert src.image_frames[CAMERA] == {0, 1, 2, 3} and "metadata" in src.notes[0]
    assert src.images.read(CAMERA, 2).shape == (48, 32, 3)
    assert "--focal-px" in read_monocular(tmp_path / "clip.mp4", focal_px=40.0).notes[0]
    # a folder of frames (sorted by name), and what --format auto says
    folder = tmp_path / "frames"
    folder.mkdir()
    import cv2

    for i, f in enumerate(frames):
        cv2.imwrite(str(folder / f"img_{i:03d}.png"), f)
    src = read_monocular(folder)
    assert src.image_frames[CAMERA] == {0, 1, 2, 3} and "default" in src.notes[0]
    assert is_monocular_source(folder) and is_monocular_source(tmp_path / "clip.mp4")
    assert detect_format(tmp_path / "clip.mp4")[0] == "video" and detect_format(folder)[0] == "video"
    (folder / "intri.yml").write_text("%YAML:1.0\n")  # a calibrated capture is not one video
    assert not is_monocular_source(folder)


def test_similarity_alignment_recovers_scale_rotation_translation():
    import roma
    import torch

    from avatarctl.geometry.align import similarity_align

    rng = np.random.default_rng(0)
    X = rng.normal(size=(30, 3))
    R = roma.rotvec_to_rotmat(torch.tensor([0.3, -1.2, 0.5], dtype=torch.float64)).numpy()
    Y = 1.7 * X @ R.T + np.array([0.2, -3.0, 1.0])
    sim = similarity_align(X, Y)
    assert sim.scale == pytest.approx(1.7) and np.allclose(sim.R, R) and np.allclose(sim.apply(X), Y)
    with pytest.raises(ValueError):
        similarity_align(X[:2], Y[:2])


# ---- the synth phone layout ------------------------------------------------------------------------------------------
def test_synth_phone_writes_one_video_and_the_truth_beside_it(tmp_path):
    from avatarctl.io.monocular import read_monocular
    from avatarctl.synth import SynthConfig, synthesize

    cfg = SynthConfig.preset("phone", size=64, width=40, train_frames=3, test_frames=2, supersample=1)
    assert cfg.image_width == 40 and SynthConfig.preset("phone").size >= 512
    res = synthesize(tmp_path / "out", cfg)
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["gt", "video.mp4"]  # nothing else a user lacks
    truth = tmp_path / "out" / "gt" / "capture"
    for n in ("intri.yml", "extri.yml", "motion.npz", "masks", "images", "split.json", "gt"):
        assert (truth / n).exists(), n
    src = read_monocular(tmp_path / "out" / "video.mp4")
    cam, true_cam = src.cameras[0], res.cameras[0]
    assert (cam.width, cam.height) == (40, 64) and sorted(src.image_frames["cam00"]) == list(range(5))
    assert cam.K[0, 0] == pytest.approx(true_cam.K[0, 0], rel=1e-3) and "metadata" in src.notes[0]
    assert np.allclose(true_cam.dist, 0)  # a phone video is undistorted
    import cv2

    first = cv2.imread(str(truth / "images" / "cam00" / "000000.jpg"))[..., ::-1].astype(float)
    assert np.abs(src.images.read("cam00", 0).astype(float) - first).mean() < 6  # the same frame, H.264-coded


# ---- the monocular fit (anny, exact 2D keypoints) --------------------------------------------------------------------
def _turning_subject(frames: int, headings_deg):
    import roma
    import torch

    from avatarctl.body.anny_model import AnnyBody
    from avatarctl.body.fit_keypoints import FIT_BONES, AnnyKeypoints, ImageKeypointTargets
    from avatarctl.ingest.keypoints import KEYPOINT_NAMES

    kp = AnnyKeypoints(AnnyBody(), KEYPOINT_NAMES)
    A = torch.tensor([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]], dtype=torch.float64)  # anny (z up) -> camera (y down)
    head = torch.tensor(np.radians(headings_deg), dtype=torch.float64)
    R = A @ roma.rotvec_to_rotmat(torch.stack([torch.zeros(frames), torch.zeros(frames), head], -1).double())
    t = torch.tensor([[0.1, 0.15, 3.2]] * frames, dtype=torch.float64)
    rot = 0.05 * torch.randn(frames, len(FIT_BONES), 3, generator=torch.Generator().manual_seed(0),
                             dtype=torch.float64)
    rot[:, kp.hinges.slot] = 0.2 * kp.hinges.axis
    pheno = torch.tensor([0.3, 0.5, 0.5, 0.5, 0.6, 0.5], dtype=torch.float64)
    with torch.no_grad():
        K, V = kp(kp.pose_matrices(rot, R, t), pheno)
    f_px = 420.0
    P = np.array([[[f_px, 0, 143.5, 0], [0, f_px, 255.5, 0], [0, 0, 1, 0]]])
    x = K.numpy() @ P[0, :, :3].T
    uv = x[..., :2] / x[..., 2:] + np.random.default_rng(1).normal(0, 0.5, (frames, K.shape[1], 2))
    targets = ImageKeypointTargets(KEYPOINT_NAMES, P, np.array([f_px]), uv[:, None],
                                   np.ones((frames, 1, len(KEYPOINT_NAMES))))
    return kp, targets, K.numpy(), R.numpy()


def test_initial_root_2d_finds_the_heading_of_a_turning_subject():
    import torch

    from avatarctl.body.fit_keypoints import initial_root_2d

    kp, targets, _, R = _turning_subject(6, [0, 60, 120, 180, 240, 300])
    with torch.no_grad():
        rest = kp.keypoints(torch.zeros(1, 21, 3, dtype=torch.float64), torch.eye(3, dtype=torch.float64)[None],
                            torch.zeros(1, 3, dtype=torch.float64), torch.zeros(6, dtype=torch.float64))[0][0].numpy()
    R0, t0 = initial_root_2d(rest, targets)
    fwd = np.array([0.0, -1.0, 0.0])  # anny faces -y: compare where the body faces, in the camera frame
    angles = [np.degrees(np.arccos(np.clip((R[f] @ fwd) @ (R0[f] @ fwd), -1, 1))) for f in range(6)]
    assert max(angles) < 40, angles
    assert np.all(np.abs(t0[:, 2] - 3.2) < 0.6)  # the depth from the torso's size


def test_monocular_fit_recovers_the_pose_the_height_and_the_floor():
    import torch

    from avatarctl.body.fit_keypoints import KeypointFitConfig, fit_keypoints
    from avatarctl.geometry.align import aligned_errors

    kp, targets, K_true, _ = _turning_subject(4, [0, 30, 60, 90])
    fit = fit_keypoints(kp, targets, KeypointFitConfig(iters=120, height_m=1.75, w_ground=1.0, w_root_smooth=1e-3))
    with torch.no_grad():
        K_fit, _ = kp(torch.as_tensor(fit.motion.pose_parameters), torch.as_tensor(fit.motion.phenotype))
    err = aligned_errors(K_fit.numpy(), K_true)[0].mean()
    assert err < 0.04, err  # < 4 cm after a similarity alignment
    assert fit.error_px.mean() < 3.0 and fit.height_m == pytest.approx(1.75, abs=0.03)
    assert fit.ground is not None and fit.ground[1] < -0.9  # the floor's normal points up: -y in the camera frame
    with pytest.raises(ValueError, match="bad keypoint-fit"):
        KeypointFitConfig(height_m=5.0)


# ---- MediaPipe's native log lines ------------------------------------------------------------------------------------
SPAM = (b"W0000 00:00:1795737024.808253   25460 inference_feedback_manager.cc:114] Feedback manager requires a model\n"
        b"I0000 00:00:1795737024.9 25461 gl_context.cc:357] GL version\n"
        b"INFO: Created TensorFlow Lite XNNPACK delegate for CPU.\n"
        b"WARNING: All log messages before absl::InitializeLog() is called are written to STDERR\n")


def test_native_log_filter_drops_absl_warnings_and_keeps_errors(capfd):
    from avatarctl.ingest.keypoints import native_log_filter

    with native_log_filter():
        with native_log_filter():  # re-entrant
            os.write(2, SPAM)
            os.write(2, b"E0000 00:00:1.0 1 calculator_graph.cc:1] a real error\n")
        print("python says", file=sys.stderr)
    os.write(2, b"W0000 00:00:1.0 1 after.cc:1] outside the filter\n")
    err = capfd.readouterr().err
    assert "inference_feedback_manager" not in err and "XNNPACK" not in err and "InitializeLog" not in err
    assert "a real error" in err and "python says" in err and "outside the filter" in err


def test_mediapipe_detector_prints_no_native_warnings(capfd):
    pytest.importorskip("mediapipe")
    from skimage import data

    from avatarctl.ingest.keypoints import PoseDetector

    with PoseDetector() as det:
        for _ in range(2):
            d = det(data.astronaut())
    assert d.found
    err = capfd.readouterr().err
    assert "W0000" not in err and "inference_feedback_manager" not in err and "XNNPACK" not in err, err


def test_detect_people_passes_its_smooth_choice_to_mediapipe(monkeypatch):
    """MediaPipe's temporal landmark filter lags behind moving limbs: the pipeline turns it off for calibrated cameras
    (the multi-view fits' joints 3.83 -> 3.19 cm on synth tight, 5.18 -> 4.35 on synth realistic) and keeps it for
    one video (docs/experiments/detector_smoothing_2026-12-01/). `detect_people(smooth=...)` reaches MediaPipe's Pose
    as `smooth_landmarks` (a stand-in module: runs without the capture extra)."""
    from types import SimpleNamespace

    from avatarctl.ingest import estimate, keypoints

    seen: list[dict] = []

    class FakePose:
        def __init__(self, **kw):
            seen.append(kw)

        def process(self, rgb):
            return SimpleNamespace(pose_landmarks=None, segmentation_mask=None)

        def close(self):
            pass

    fake_mp = SimpleNamespace(solutions=SimpleNamespace(pose=SimpleNamespace(Pose=FakePose)))
    monkeypatch.setattr(keypoints, "require_mediapipe", lambda *a, **k: fake_mp)
    image = np.zeros((300, 300, 3), np.uint8)
    for smooth in (False, True):
        estimate.detect_people(lambda c, f: image, ["cam00"], [0], masks=False, smooth=smooth)
    assert [kw["smooth_landmarks"] for kw in seen] == [False, True]
    assert all(kw["static_image_mode"] is False and kw["model_complexity"] == 1 for kw in seen)


# ---- the whole path on a synthetic phone video (MediaPipe) ----------------------------------------------------------
@pytest.mark.slow
def test_ingest_one_synthetic_phone_video_as_a_user_would(tmp_path):
    pytest.importorskip("mediapipe")
    import cv2
    import torch
    from anny.keypoints import KeypointsRegressor

    from avatarctl.body.anny_model import AnnyBody
    from avatarctl.body.motion import BodyMotion
    from avatarctl.geometry.align import aligned_errors
    from avatarctl.ingest.masks import iou
    from avatarctl.project import hash_tree
    from avatarctl.synth import SynthConfig, synthesize

    out = tmp_path / "phone"
    synthesize(out, SynthConfig.preset("phone", size=160, width=96, train_frames=10, test_frames=4))
    before = hash_tree(out)
    proj = tmp_path / "P"
    res = CliRunner().invoke(app, ["ingest", str(out / "video.mp4"), str(proj), "--keypoint-fit-iters", "100"])
    assert res.exit_code == 0, res.output
    assert hash_tree(out) == before
    assert "intrinsics" in res.output and "video metadata" in res.output and "W0000" not in res.output
    summary = json.loads((proj / "project.json").read_text())["stages"][0]["summary"]
    assert summary["format"] == "video" and summary["estimate"]["monocular"]
    # the silhouette term's two sides ran: the masks' outline closer to the projected body at the end
    assert summary["estimate"]["outline_after_cm"] < summary["estimate"]["outline_before_cm"]
    assert "outline term" in res.output
    split = json.loads((proj / "ingest" / "split.json").read_text())
    assert split["train_views"] == split["test_views"] == ["cam00"]
    assert max(split["train_frames"]) < min(split["test_frames"])  # held-out frames later in the video
    assert (proj / "ingest" / "contact_sheet.png").is_file()
    # the fit against the truth, after one similarity alignment (the video's world is its camera's)
    est = BodyMotion.load(proj / "ingest" / "body.npz")
    ref = BodyMotion.load(out / "gt" / "capture" / "motion.npz")
    ref = ref.for_frames([int(f) for f in est.frame_index])
    body = AnnyBody()
    reg = KeypointsRegressor.coco(body.model)
    with torch.no_grad():
        K_est = reg({"vertices": body.pose(est).vertices.double()}).numpy()
        K_ref = reg({"vertices": body.pose(ref).vertices.double()}).numpy()
    err = aligned_errors(K_est, K_ref)[0].mean()
    assert err < 0.10, err  # 160 px tall; the measured target (<= 4 cm) is at the phone preset's 512 px
    ious = [iou(cv2.imread(str(proj / "ingest" / "masks" / "cam00" / f"{int(f):06d}.png"), 0) > 127,
                cv2.imread(str(out / "gt" / "capture" / "masks" / "cam00" / f"{int(f):06d}.png"), 0) > 127)
            for f in est.frame_index]
    assert np.mean(ious) > 0.88, np.mean(ious)
    shutil.rmtree(proj)


def test_smpl_goes_through_the_same_monocular_fit(tmp_path):
    """`estimate_monocular` with an SMPL model file (random arrays, T-pose rest joints: tests/fixtures/smpl.py):
    the same energy, no joint limits; exact 2D keypoints of a known pose -> the pose back."""
    import torch

    from avatarctl.body import rigs
    from avatarctl.body.lbs import axis_angle_to_matrix
    from avatarctl.body.registry import load_body_model
    from avatarctl.body.smpl_keypoints import FIT_JOINTS, SmplKeypoints
    from avatarctl.geometry.align import aligned_errors
    from avatarctl.geometry.cameras import Camera
    from avatarctl.ingest.estimate import Detections, estimate_monocular
    from avatarctl.ingest.keypoints import KEYPOINT_NAMES
    from fixtures.smpl import write_random_smpl_npz

    rest = np.array([rigs.GENERIC_T_POSE[n] for n in rigs.SMPL_NAMES]) * 1.05
    rest[:, 1] += 0.25
    body = load_body_model("smpl", write_random_smpl_npz(tmp_path / "SMPL_NEUTRAL.npz", "smpl", seed=3,
                                                         rest_joints=rest))
    kp = SmplKeypoints(body, KEYPOINT_NAMES)
    frames = 4
    rot = 0.1 * torch.randn(frames, len(FIT_JOINTS), 3, generator=torch.Generator().manual_seed(0),
                            dtype=torch.float64)
    for n in ("left_wrist", "right_wrist", "left_collar", "right_collar", "left_foot", "right_foot"):
        rot[:, FIT_JOINTS.index(n)] = 0.0
    R = axis_angle_to_matrix(torch.tensor([[np.pi, 0.0, 0.0]] * frames, dtype=torch.float64))  # y up -> y down
    t = torch.tensor([[0.0, 0.1, 3.0]] * frames, dtype=torch.float64)
    with torch.no_grad():
        K, _ = kp.keypoints(rot, R, t, torch.zeros(kp.num_shape, dtype=torch.float64))
    cam = Camera(name="cam00", K=np.array([[400.0, 0, 143.5], [0, 400.0, 255.5], [0, 0, 1]]), R=np.eye(3),
                 T=np.zeros(3), width=288, height=512)
    uv = cam.project(K.numpy().reshape(-1, 3)).reshape(frames, -1, 2)
    kpts = np.full((frames, 1, len(KEYPOINT_NAMES), 2), np.nan)
    conf = np.zeros((frames, 1, len(KEYPOINT_NAMES)))
    for j, n in enumerate(kp.names):
        kpts[:, 0, KEYPOINT_NAMES.index(n)] = uv[:, j]
        conf[:, 0, KEYPOINT_NAMES.index(n)] = 1.0
    det = Detections(cams=["cam00"], frames=list(range(frames)), names=KEYPOINT_NAMES, keypoints=kpts,
                     confidence=conf)
    est = estimate_monocular(det, cam, body, 150, 30.0, np.ones(frames, bool), height_m=None,
                             silhouette_weight=0.0)
    assert est.motion.body_model == "smpl" and est.kept == list(range(frames)) and est.report.monocular
    assert est.report.mean_reprojection_px < 3.0, est.report.mean_reprojection_px
    with torch.no_grad():
        K_fit = body.joints(est.motion).double().numpy()  # SMPL's joints of the fitted motion
        K_true = body.joints(kp.to_motion(rot, R, t, torch.zeros(kp.num_shape, dtype=torch.float64))).double().numpy()
    assert aligned_errors(K_fit[:, :22], K_true[:, :22])[0].mean() < 0.05


def test_one_camera_contact_sheet_puts_the_frames_side_by_side(tmp_path):
    import cv2

    from avatarctl.ingest.contact_sheet import Tile, write_contact_sheet

    rgb = np.full((64, 32, 3), 90, np.uint8)
    body = np.zeros((64, 32), bool)
    body[10:50, 8:24] = True
    tiles = [Tile("cam00", f, rgb, body, body) for f in (0, 5, 9)]
    write_contact_sheet(tmp_path / "s.png", tiles, ["cam00"], [0, 5, 9], width=40)
    sheet = cv2.imread(str(tmp_path / "s.png"))
    assert sheet.shape == (80, 120, 3)
    assert sheet[40, 20, 2] > sheet[40, 2, 2]  # the body is tinted red (BGR)


def test_one_video_without_the_capture_extra_is_one_line(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "mediapipe", None)  # import mediapipe -> ImportError, installed or not
    _write_video(tmp_path / "clip.mp4", [np.full((48, 32, 3), 60, np.uint8)] * 12)
    res = CliRunner().invoke(app, ["ingest", str(tmp_path / "clip.mp4"), str(tmp_path / "P")])
    err = res.stderr.strip()
    assert res.exit_code == 2 and len(err.splitlines()) == 1 and "avatarctl[capture]" in err, err
    assert not (tmp_path / "P").exists()


def _striped_video(moves: bool) -> tuple[list[np.ndarray], object]:
    """12 frames of 96 x 160 with a person (a bright box with a mask) walking across the background. Static: a
    curtain of vertical stripes (period 24 px, the synth phone video's case). `moves`: a random texture instead (a
    pan over a periodic curtain is ambiguous to any method), and the whole picture pans 4 px a frame."""
    import cv2

    from avatarctl.ingest.estimate import Detections

    H, W, n = 160, 96, 12
    if moves:
        noise = np.random.default_rng(0).uniform(0, 255, (H, W)).astype(np.float32)
        curtain = np.repeat(cv2.GaussianBlur(noise, (0, 0), 2.0)[..., None], 3, axis=2)
    else:
        curtain = np.repeat((120 + 60 * np.sin(2 * np.pi * np.arange(W) / 24))[None, :, None], H, axis=0)
        curtain = curtain.repeat(3, axis=2)
    frames, masks = [], {}
    for k in range(n):
        img, m = curtain.copy(), np.zeros((H, W), bool)
        m[40:130, 10 + 5 * k:30 + 5 * k] = True
        img[m] = (200, 60, 40)
        if moves:
            img, m = np.roll(img, 4 * k, axis=1), np.roll(m, 4 * k, axis=1)
        frames.append(img.astype(np.uint8))
        masks[("cam00", k)] = cv2.imencode(".png", m.astype(np.uint8) * 255)[1].tobytes()
    det = Detections(cams=["cam00"], frames=list(range(n)), names=("nose",), keypoints=np.zeros((n, 1, 1, 2)),
                     confidence=np.ones((n, 1, 1)))
    det.masks.update(masks)
    return frames, det


def test_a_striped_background_behind_a_static_camera_is_not_a_moving_camera():
    """Phase correlation can peak one stripe period away on a periodic background; the shift then has to explain the
    background better than no shift does (ingest once refused a static synth phone video in front of a curtain)."""
    from avatarctl.ingest.estimate import camera_shift_px

    frames, det = _striped_video(moves=False)
    assert camera_shift_px(lambda f: frames[f], det) < 2.0
    frames, det = _striped_video(moves=True)
    assert camera_shift_px(lambda f: frames[f], det) > 30.0  # 44 px between the first and the last frame
