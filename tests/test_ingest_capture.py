"""The own-capture path of ingest: videos, robust triangulation, the anny keypoint fit, the missing-extra error,
and (when MediaPipe is installed) masks and fits estimated from a synthetic capture."""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from avatarctl.cli.app import app
from fixtures.captures import make_easymocap_capture, ring_cameras
from fixtures.cli_errors import assert_one_line_error

ARM_RAISE = (0.0, -0.9, 0.0)  # upperarm01.L: the left arm raised sideways, out of the torso's silhouette (front view)


def _cli(*args: str):
    return CliRunner().invoke(app, ["ingest", *args])


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    return make_easymocap_capture(tmp_path_factory.mktemp("cap") / "cap", frames=[0, 1, 2, 3], n_cams=3)


# ---- triangulation --------------------------------------------------------------------------------------------
def test_triangulation_recovers_points_and_rejects_an_outlier_view():
    from avatarctl.geometry.triangulate import project, projection_matrices, triangulate_dlt, triangulate_robust

    cams = ring_cameras(6, 256)
    P = projection_matrices(cams)
    rng = np.random.default_rng(0)
    X = rng.uniform(-0.4, 0.4, (50, 3)) + np.array([0, 0, 0.9])
    x, z = project(P, X)  # [points, cams, 2]
    assert (z > 0).all()
    x = x + rng.normal(0, 0.3, x.shape)
    x[:, 2] += np.array([25.0, -30.0])  # camera 2 is off by ~40 px for every point: an outlier view
    conf = np.ones(x.shape[:2])
    naive = triangulate_dlt(P, x, conf)
    tri = triangulate_robust(P, x, conf, threshold_px=5.0)
    assert tri.valid.all()
    err = np.linalg.norm(tri.X - X, axis=-1)
    assert err.max() < 0.01, err.max()  # < 1 cm
    assert np.linalg.norm(naive - X, axis=-1).mean() > 3 * err.mean()  # the outlier spoils plain DLT
    assert tri.rejected[:, 2].all() and not tri.rejected[:, [0, 1, 3, 4, 5]].any()
    assert np.nanmax(tri.error_px) < 2.0
    # a point seen with confidence by one camera only is not triangulated
    conf1 = np.zeros_like(conf)
    conf1[:, 0] = 1.0
    assert not triangulate_robust(P, x, conf1).valid.any()


def test_dlt_is_exact_without_noise():
    from avatarctl.geometry.triangulate import project, projection_matrices, triangulate_dlt

    cams = ring_cameras(3, 128)
    P = projection_matrices(cams)
    X = np.array([[0.1, -0.2, 1.0], [0.0, 0.0, 0.5]])
    x, _ = project(P, X)
    np.testing.assert_allclose(triangulate_dlt(P, x, np.ones(x.shape[:2])), X, atol=1e-8)


# ---- anny keypoint fit ------------------------------------------------------------------------------------------
def test_anny_fit_recovers_a_known_pose_from_its_keypoints():
    import torch

    from avatarctl.body.anny_model import AnnyBody
    from avatarctl.body.fit_keypoints import (FIT_BONES, AnnyKeypoints, KeypointFitConfig, KeypointTargets,
                                              fit_keypoints)
    from avatarctl.ingest.keypoints import KEYPOINT_NAMES

    body = AnnyBody()
    kp = AnnyKeypoints(body, KEYPOINT_NAMES)
    g = torch.Generator().manual_seed(0)
    rot = 0.35 * torch.randn(3, len(FIT_BONES), 3, generator=g, dtype=torch.float64)
    with torch.no_grad():  # knees and elbows bend about their hinge axes only, within their limits (a body can)
        h = kp.hinges
        rot[:, h.slot] = (h.lo + (h.hi - h.lo) * torch.rand(3, len(h.slot), generator=g, dtype=torch.float64))[
            ..., None] * h.axis
    assert float(kp.limit_penalty(rot).max()) == 0.0
    root = torch.tensor([[0.2, -0.3, 2.0], [0.25, -0.3, 2.1], [0.3, -0.25, 2.2]], dtype=torch.float64)
    import roma

    pose = kp.pose_matrices(rot, roma.rotvec_to_rotmat(root), torch.tensor([[0.5, 0.2, 1.0]] * 3, dtype=torch.float64))
    pheno = torch.tensor([0.3, 0.5, 0.5, 0.5, 0.6, 0.5], dtype=torch.float64)
    with torch.no_grad():
        K, V = kp(pose, pheno)
    targets = KeypointTargets(KEYPOINT_NAMES, K.numpy(), np.ones(K.shape[:2]))
    fit = fit_keypoints(kp, targets, KeypointFitConfig(iters=250))
    with torch.no_grad():
        K2, V2 = kp(torch.as_tensor(fit.motion.pose_parameters, dtype=torch.float64),
                    torch.as_tensor(fit.motion.phenotype, dtype=torch.float64))
    assert (K2 - K).norm(dim=-1).mean() < 0.01  # < 1 cm mean keypoint (joint) error
    assert (V2 - V).norm(dim=-1).mean() < 0.02  # < 2 cm mean vertex error
    assert fit.error_m.max() < 0.02
    motion = fit.to_motion([5, 6, 7])
    assert motion.body_model == "anny" and motion.pose_parameters.shape == (3, 104, 4, 4)


def test_anny_keypoint_offsets_turn_with_their_bones():
    """A keypoint's offset (in its bone's rest frame) is added after the bone's rotation from rest to the pose, the
    rotation of the skinning transform `BodyModel.pose` gives (what benchmarks.keypoint_offsets measures in); a
    keypoint without an offset stays anny's COCO point; an unknown bone is refused."""
    import roma
    import torch

    from avatarctl.body.anny_model import AnnyBody
    from avatarctl.body.fit_keypoints import FIT_BONES, AnnyKeypoints
    from avatarctl.ingest.keypoints import KEYPOINT_NAMES

    body = AnnyBody()
    offsets = {"nose": ("head", (0.01, 0.03, -0.02)), "left_hip": ("pelvis.L", (0.0, -0.01, 0.04)),
               "right_knee": ("lowerleg01.R", (0.02, 0.0, 0.01))}
    plain, shifted = AnnyKeypoints(body, KEYPOINT_NAMES), AnnyKeypoints(body, KEYPOINT_NAMES, offsets=offsets)
    g = torch.Generator().manual_seed(3)
    rot = 0.4 * torch.randn(2, len(FIT_BONES), 3, generator=g, dtype=torch.float64)
    R = roma.rotvec_to_rotmat(torch.tensor([[0.1, 0.2, 1.0], [-0.3, 0.1, 2.5]], dtype=torch.float64))
    t = torch.tensor([[0.1, 0.0, 0.9], [0.2, -0.1, 0.9]], dtype=torch.float64)
    shape = torch.tensor([0.5, -0.3, 0.0, 0.2, 0.0, 0.1], dtype=torch.float64)
    with torch.no_grad():
        K0, V0 = plain.keypoints(rot, R, t, shape)
        K1, V1 = shifted.keypoints(rot, R, t, shape)
        M = body.pose(plain.to_motion(rot, R, t, shape)).joint_transforms.double()
    assert torch.equal(V0, V1)
    for j, n in enumerate(KEYPOINT_NAMES):
        if n in offsets:
            bone, o = offsets[n]
            want = M[:, body.joint_names.index(bone), :3, :3] @ torch.tensor(o, dtype=torch.float64)
            torch.testing.assert_close(K1[:, j] - K0[:, j], want, atol=1e-5, rtol=0)
            assert float((K1[:, j] - K0[:, j]).norm(dim=-1).min()) > 0.02
        else:
            assert torch.equal(K1[:, j], K0[:, j])
    with pytest.raises(ValueError, match="bones anny does not have"):
        AnnyKeypoints(body, KEYPOINT_NAMES, offsets={"nose": ("skull", (0.0, 0.0, 0.0))})


def test_mediapipe_offsets_name_known_keypoints_and_bones_and_stay_small():
    from avatarctl.body.anny_model import AnnyBody
    from avatarctl.ingest.keypoints import KEYPOINT_BONES, KEYPOINT_NAMES, MEDIAPIPE_ANNY_OFFSETS

    names = AnnyBody().joint_names
    assert set(KEYPOINT_BONES) == set(KEYPOINT_NAMES) and set(KEYPOINT_BONES.values()) <= set(names)
    assert MEDIAPIPE_ANNY_OFFSETS and set(MEDIAPIPE_ANNY_OFFSETS) <= set(KEYPOINT_NAMES)
    for n, (bone, o) in MEDIAPIPE_ANNY_OFFSETS.items():
        assert bone == KEYPOINT_BONES[n] and np.linalg.norm(o) < 0.1  # metres: a definition, not a body part
        if n.startswith("left_"):  # left-right symmetric: x mirrored, y and z shared
            _, r = MEDIAPIPE_ANNY_OFFSETS["right_" + n[5:]]
            np.testing.assert_allclose(o, (-r[0], r[1], r[2]), atol=1e-9)


def test_detections_round_trip_and_a_damaged_file_is_one_line(tmp_path):
    from avatarctl.errors import InputError
    from avatarctl.ingest.estimate import Detections

    rng = np.random.default_rng(0)
    kp = rng.uniform(0, 100, size=(3, 2, 4, 2))
    kp[1, 0] = np.nan
    det = Detections(cams=["a", "b"], frames=[4, 5, 7], names=("nose", "l", "r", "x"), keypoints=kp,
                     confidence=rng.uniform(size=(3, 2, 4)))
    det.save(tmp_path / "k.npz")
    back = Detections.load(tmp_path / "k.npz")
    assert back.cams == det.cams and back.frames == det.frames and back.names == det.names
    np.testing.assert_allclose(back.keypoints, kp, atol=1e-4)
    np.testing.assert_allclose(back.confidence, det.confidence, atol=1e-6)
    (tmp_path / "bad.npz").write_bytes(b"not an npz")
    with pytest.raises(InputError, match="bad keypoint detections"):
        Detections.load(tmp_path / "bad.npz")


def _plate_scene(frames: int = 12, size: int = 96, shift: int = 3):
    """A textured static background, a striped ellipse crossing it; the truth masks, and a detector's masks that
    miss the truth by `shift` px (grown on one side, shrunk on the other, as MediaPipe's coarse outline does)."""
    import cv2

    rng = np.random.default_rng(0)
    bg = cv2.GaussianBlur(rng.integers(0, 256, (size, size, 3)).astype(np.uint8), (5, 5), 0)
    yy, xx = np.mgrid[:size, :size]
    images, truth, detected = [], [], []
    for i in range(frames):
        cx, cy = 20 + i * (size - 40) / (frames - 1), size / 2
        inside = ((xx - cx) / 14) ** 2 + ((yy - cy) / 30) ** 2 <= 1
        person = np.where(((yy // 3) % 2 == 0)[..., None], [200, 40, 40], [40, 40, 200]).astype(np.uint8)
        images.append(np.where(inside[..., None], person, bg))
        truth.append(inside)
        detected.append(np.roll(inside, shift, axis=1))  # too much on one side, too little on the other
    return bg, np.stack(images), np.stack(truth), np.stack(detected)


def test_plate_estimated_from_the_frames_refines_a_detector_mask():
    from avatarctl.ingest.masks import estimate_plate, iou, refine_mask

    bg, images, truth, detected = _plate_scene()
    plate, known = estimate_plate(images, detected, margin_px=2)
    assert known.mean() > 0.9  # the person moves: almost every pixel is uncovered in enough frames
    assert np.abs(plate[known].astype(int) - bg[known]).max() <= 1  # where known, the plate is the background
    raw = np.mean([iou(d, t) for d, t in zip(detected, truth)])
    refined = [refine_mask(im, plate, known, d, band_px=4) for im, d in zip(images, detected)]
    assert raw < 0.93 and np.mean([iou(r, t) for r, t in zip(refined, truth)]) > 0.98
    # where the plate is not known the detector's mask is kept as it is
    nothing = np.zeros_like(known)
    assert np.array_equal(refine_mask(images[0], plate, nothing, detected[0], band_px=4), detected[0])
    with pytest.raises(ValueError, match="differ"):
        estimate_plate(images[:, :-1], detected, margin_px=2)


def test_sharpen_outline_places_a_low_contrast_outline_at_half_coverage():
    """A printed disk whose colour differs from the background by ~55 (RGB distance), drawn with anti-aliased edges:
    a half-covered outline pixel differs by ~27, under any fixed threshold that noise allows. A mask 1 px too thin
    (or too fat) comes back to the pixels covered at least half."""
    import cv2

    from avatarctl.ingest.masks import color_difference, iou, sharpen_outline

    ss, size = 8, 64
    yy, xx = (np.mgrid[:size * ss, :size * ss] + 0.5) / ss
    inside = (xx - 31.3) ** 2 + (yy - 32.6) ** 2 <= 19.4 ** 2
    print_ = np.where(((yy.astype(int) // 2) % 2 == 0)[..., None], [150, 120, 100], [100, 150, 120])
    hi = np.where(inside[..., None], print_, [100, 100, 100]).astype(np.float32)
    rgb = cv2.resize(hi, (size, size), interpolation=cv2.INTER_AREA)  # box filter: mixed outline pixels
    cover = cv2.resize(inside.astype(np.float32), (size, size), interpolation=cv2.INTER_AREA)
    truth = cover >= 0.5
    plate = np.full((size, size, 3), 100, np.uint8)
    diff = color_difference(np.rint(rgb).astype(np.uint8), plate)
    assert 15 < diff[(cover > 0.4) & (cover < 0.6)].mean() < 35  # the mixed pixels: low contrast
    known = np.ones((size, size), bool)
    disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (3, 3))
    thin = cv2.erode(truth.astype(np.uint8), disk) > 0
    fat = cv2.dilate(truth.astype(np.uint8), disk) > 0
    for start in (thin, fat):
        out = sharpen_outline(diff, known, start)
        assert iou(start, truth) < 0.92 and iou(out, truth) > 0.97
    # where the plate is not known the mask is kept as it is
    assert np.array_equal(sharpen_outline(diff, np.zeros_like(known), thin), thin)


def test_refine_masks_replaces_every_detected_mask_and_reports_it():
    import cv2

    from avatarctl.ingest.estimate import Detections, refine_masks
    from avatarctl.ingest.masks import iou

    bg, images, truth, detected = _plate_scene(shift=2)  # the band at 96 px: 2 px (`MASK_BAND` of the diagonal)
    frames = list(range(len(images)))
    det = Detections(cams=["a"], frames=frames, names=("nose",), keypoints=np.zeros((len(frames), 1, 1, 2)),
                     confidence=np.ones((len(frames), 1, 1)),
                     masks={("a", f): cv2.imencode(".png", detected[f].astype(np.uint8) * 255)[1].tobytes()
                            for f in frames})
    seen = []
    out, report = refine_masks(det, lambda c, f: images[f], progress=lambda r: seen.append(r.done))
    assert report.plate_known["a"] > 0.9 and report.band_px["a"] == 2 and report.changed["a"] > 0.05
    assert np.mean([iou(out.mask("a", f), truth[f]) for f in frames]) > 0.97
    assert np.array_equal(det.mask("a", 0), detected[0])  # the input is left as it was
    assert seen[-1] == len(frames)


def test_refine_masks_takes_the_captures_plate_where_it_agrees_with_the_frames():
    """The capture's plate refines where the frames alone know no plate (two frames: a pixel needs three), and is
    refused for the estimate when it disagrees with the frames (shot brighter)."""
    import cv2

    from avatarctl.ingest.estimate import Detections, refine_masks
    from avatarctl.ingest.masks import iou

    bg, images, truth, detected = _plate_scene(shift=2)

    def refined(frames, plates):
        det = Detections(cams=["a"], frames=frames, names=("nose",), keypoints=np.zeros((len(frames), 1, 1, 2)),
                         confidence=np.ones((len(frames), 1, 1)),
                         masks={("a", f): cv2.imencode(".png", detected[f].astype(np.uint8) * 255)[1].tobytes()
                                for f in frames})
        out, report = refine_masks(det, lambda c, f: images[f], plate_of=None if plates is None else plates.get)
        return np.mean([iou(out.mask("a", f), truth[f]) for f in frames]), report

    two = [5, 6]
    raw = np.mean([iou(detected[f], truth[f]) for f in two])
    score, report = refined(two, None)
    assert report.plate["a"] == "estimated" and report.plate_known["a"] == 0.0 and score == raw
    score, report = refined(two, {"a": bg})
    assert report.plate["a"] == "capture" and report.plate_known["a"] == 1.0 and score > raw + 0.05
    every = list(range(len(images)))
    own, report = refined(every, {"a": bg})
    assert report.plate["a"] == "capture" and own > 0.97
    brighter = np.clip(bg.astype(int) * 5 // 4 + 10, 0, 255).astype(np.uint8)
    score, report = refined(every, {"a": brighter})
    assert report.plate["a"] == "estimated" and score == refined(every, None)[0]


def _stand_in_detector(monkeypatch, capture, mask_of) -> list[bool]:
    """`--masks mediapipe` without MediaPipe: `detect_people` returns, for every view, `mask_of(camera, true mask)`
    (the capture's mask file) as the detected person mask, and zero keypoints. Returns the list its calls' `smooth`
    arguments are appended to."""
    import cv2

    from avatarctl.ingest import estimate, keypoints

    smooths: list[bool] = []

    def fake_detect(read_view, cams, frames, masks, progress=None, smooth=False):
        smooths.append(smooth)
        J = len(keypoints.KEYPOINT_NAMES)
        det = estimate.Detections(cams=list(cams), frames=list(frames), names=keypoints.KEYPOINT_NAMES,
                                  keypoints=np.zeros((len(frames), len(cams), J, 2)),
                                  confidence=np.ones((len(frames), len(cams), J)))
        for c in cams:
            for f in frames:
                m = mask_of(c, cv2.imread(str(capture.root / "masks" / c / f"{f:06d}.png"), 0) > 0)
                det.masks[(c, f)] = cv2.imencode(".png", m.astype(np.uint8) * 255)[1].tobytes()
        return det

    monkeypatch.setattr(keypoints, "require_mediapipe", lambda *a, **k: None)
    monkeypatch.setattr(estimate, "detect_people", fake_detect)
    return smooths


def test_ingest_refines_detected_masks_unless_told_not_to(capture, tmp_path, monkeypatch):
    """`--masks mediapipe` with a stand-in detector whose masks are the truth shifted by 2 px: ingest writes them
    refined against the estimated plates (closer to the truth, the report in the summary), or as detected with
    `--no-refine-masks`."""
    import cv2

    from avatarctl.ingest.masks import iou

    smooths = _stand_in_detector(monkeypatch, capture, lambda c, truth: np.roll(truth, 2, axis=1))
    scores = {}
    for name, extra in (("refined", []), ("detected", ["--no-refine-masks"])):
        proj = tmp_path / name
        res = _cli(str(capture.root), str(proj), "--masks", "mediapipe", "--fits", "files", "--no-contact-sheet",
                   *extra)
        assert res.exit_code == 0, res.output
        summary = json.loads((proj / "project.json").read_text())["stages"][0]["summary"]
        refined = summary["estimate"]["masks_refined"]
        assert (refined is None) == (name == "detected")
        assert ("masks refined" in res.output) == (name == "refined")
        scores[name] = np.mean([iou(cv2.imread(str(proj / "ingest" / "masks" / c.name / f"{f:06d}.png"), 0) > 0,
                                    cv2.imread(str(capture.root / "masks" / c.name / f"{f:06d}.png"), 0) > 0)
                                for c in capture.cameras for f in capture.frames])
    assert scores["refined"] > scores["detected"] + 0.01, scores
    assert smooths == [False, False]  # calibrated cameras: MediaPipe's landmark filter off (one video keeps it)


def test_auto_masks_with_plates_refine_the_detectors_masks_against_them(capture, tmp_path, monkeypatch):
    """A capture with plates and no masks: `--masks auto` takes MediaPipe's masks refined against the capture's plates
    when MediaPipe is installed (a stand-in detector here: the truth shifted by 2 px), and mattes the plates when it is
    not."""
    cap = tmp_path / "cap"
    shutil.copytree(capture.root, cap)
    shutil.rmtree(cap / "masks")
    monkeypatch.setitem(sys.modules, "mediapipe", None)
    res = _cli(str(cap), str(tmp_path / "matted"), "--frames", "0,3", "--no-contact-sheet")
    assert res.exit_code == 0, res.output
    summary = json.loads((tmp_path / "matted" / "project.json").read_text())["stages"][0]["summary"]
    assert summary["masks"] == "background"
    _stand_in_detector(monkeypatch, capture, lambda c, truth: np.roll(truth, 2, axis=1))
    res = _cli(str(cap), str(tmp_path / "proj"), "--frames", "0,3", "--no-contact-sheet")
    assert res.exit_code == 0, res.output
    summary = json.loads((tmp_path / "proj" / "project.json").read_text())["stages"][0]["summary"]
    assert summary["masks"] == "mediapipe"
    plates = summary["estimate"]["masks_refined"]["plate"]
    assert set(plates) == {c.name for c in capture.cameras} and set(plates.values()) == {"capture"}
    assert "against the capture's plates" in " ".join(res.output.split())
    # a plate of another size than its camera is left out of the refinement (that camera's plate estimated)
    import cv2

    first = capture.cameras[0].name
    plate = next((cap / "background").glob(f"{first}.*"))
    cv2.imwrite(str(plate), cv2.resize(cv2.imread(str(plate)), (40, 30)))
    res = _cli(str(cap), str(tmp_path / "small"), "--frames", "0,3", "--no-contact-sheet")
    assert res.exit_code == 0, res.output
    plates = json.loads((tmp_path / "small" / "project.json").read_text())["stages"][0]["summary"]["estimate"][
        "masks_refined"]["plate"]
    assert plates[first] == "estimated" and {plates[c.name] for c in capture.cameras[1:]} == {"capture"}


def test_ingest_names_a_camera_whose_masks_are_not_the_person(capture, tmp_path, monkeypatch):
    """A stand-in detector whose last camera "segments" a square in the corner instead of the person: ingest still
    succeeds, names that camera (and only it) in one warning with the fix, and records each camera's share."""
    cams = [c.name for c in capture.cameras]

    def mask_of(cam: str, truth: np.ndarray) -> np.ndarray:
        if cam != cams[-1]:
            return truth
        other = np.zeros_like(truth)
        other[:20, :20] = True  # something else
        return other

    _stand_in_detector(monkeypatch, capture, mask_of)
    proj = tmp_path / "proj"
    res = _cli(str(capture.root), str(proj), "--masks", "mediapipe", "--fits", "files", "--no-contact-sheet")
    assert res.exit_code == 0, res.output
    flat = " ".join(res.output.split())
    assert f"camera(s) {cams[-1]}" in flat and "--masks files" in flat
    assert all(f"camera(s) {c}" not in flat for c in cams[:-1])
    shares = json.loads((proj / "project.json").read_text())["stages"][0]["summary"]["vertices_inside_masks_per_camera"]
    assert set(shares) == set(cams) and shares[cams[-1]] < 0.2 and min(shares[c] for c in cams[:-1]) > 0.8


def test_anny_joint_limits_allow_bending_and_punish_a_backward_knee_or_elbow():
    import torch

    from avatarctl.body.anny_model import AnnyBody
    from avatarctl.body.fit_keypoints import FIT_BONES, AnnyKeypoints, KeypointFitConfig
    from avatarctl.ingest.keypoints import KEYPOINT_NAMES

    kp = AnnyKeypoints(AnnyBody(), KEYPOINT_NAMES)
    knee, elbow = FIT_BONES.index("lowerleg01.L"), FIT_BONES.index("lowerarm01.R")
    own_x = torch.as_tensor(np.asarray(kp.body.model.reference_bone_orientations), dtype=torch.float64)[
        kp.body.joint_names.index("lowerarm01.R")][:, 0]
    rot = torch.zeros(6, len(FIT_BONES), 3, dtype=torch.float64)
    rot[1, knee, 0] = np.deg2rad(90)  # a knee bent forward: allowed
    rot[2, elbow] = np.deg2rad(60) * own_x / own_x.norm()  # an elbow bent: allowed
    rot[3, knee, 0] = np.deg2rad(-30)  # the knee bent backwards by 30 deg (25 past the limit)
    rot[4, knee, 2] = np.deg2rad(30)  # the knee twisted by 30 deg (20 past the limit)
    rot[5, elbow] = np.deg2rad(-70) * own_x / own_x.norm()  # the elbow straightened 30 deg past straight
    L = kp.limit_penalty(rot)
    assert L[:3].abs().max() < 1e-12
    assert float(L[3]) == pytest.approx(np.deg2rad(25) ** 2, rel=1e-6)
    assert float(L[4]) == pytest.approx(np.deg2rad(20) ** 2, rel=1e-6)
    assert float(L[5]) == pytest.approx(np.deg2rad(30) ** 2, rel=1e-6)
    with pytest.raises(ValueError):
        KeypointFitConfig(w_limits=-1.0)


def test_rigid_align_recovers_rigid_motions_batched_and_weighted():
    from scipy.spatial.transform import Rotation

    from avatarctl.geometry.align import rigid_align

    rng = np.random.default_rng(1)
    src = rng.normal(size=(4, 6, 3))
    R = Rotation.from_rotvec(rng.normal(size=(4, 3))).as_matrix()
    t = rng.normal(size=(4, 3))
    dst = np.einsum("bij,bnj->bni", R, src) + t[:, None]
    R2, t2 = rigid_align(src, dst)
    np.testing.assert_allclose(R2, R, atol=1e-9)
    np.testing.assert_allclose(t2, t, atol=1e-9)
    bad = dst.copy()
    bad[:, 0] += 5.0  # an outlier given no weight leaves the motion exact; given weight, it does not
    w = np.ones((4, 6))
    w[:, 0] = 0.0
    R3, t3 = rigid_align(src, bad, w)
    np.testing.assert_allclose(R3, R, atol=1e-9)
    np.testing.assert_allclose(t3, t, atol=1e-9)
    assert np.abs(rigid_align(src, bad)[1] - t).max() > 0.1
    R4, _ = rigid_align(src[0], dst[0] * np.array([1.0, 1.0, -1.0]))  # a reflection: still a rotation
    assert np.isclose(np.linalg.det(R4), 1.0)


def test_estimate_fits_from_detections_skips_frames_without_a_person():
    """detect -> triangulate -> fit wiring without MediaPipe: detections are anny's own keypoints projected into six
    cameras (one view of frame 1 is an outlier); frame 2 has no person in any view and must be skipped."""
    import torch

    from avatarctl.body.anny_model import AnnyBody
    from avatarctl.body.fit_keypoints import FIT_BONES, AnnyKeypoints
    from avatarctl.geometry.triangulate import project, projection_matrices
    from avatarctl.ingest.estimate import Detections, estimate_fits
    from avatarctl.ingest.keypoints import KEYPOINT_NAMES

    body = AnnyBody()
    kp = AnnyKeypoints(body, KEYPOINT_NAMES)
    cams = [c.pinhole() for c in ring_cameras(6, 256)]
    rot = torch.zeros(3, len(FIT_BONES), 3, dtype=torch.float64)
    rot[:, FIT_BONES.index("upperleg01.L"), 0] = torch.tensor([0.2, 0.4, 0.6], dtype=torch.float64)
    with torch.no_grad():
        K, _ = kp(kp.pose_matrices(rot, torch.eye(3, dtype=torch.float64).expand(3, 3, 3),
                                   torch.zeros(3, 3, dtype=torch.float64)), torch.full((6,), 0.5, dtype=torch.float64))
    x, _ = project(projection_matrices(cams), K.numpy().reshape(-1, 3))  # [frames * joints, cams, 2]
    x = x.reshape(3, len(KEYPOINT_NAMES), 6, 2).transpose(0, 2, 1, 3).copy()  # [frames, cams, joints, 2]
    conf = np.ones(x.shape[:3])
    x[1, 4] += 30.0  # an outlier view
    x[2], conf[2] = np.nan, 0.0  # nobody in frame 2
    det = Detections(cams=[c.name for c in cams], frames=[10, 11, 12], names=KEYPOINT_NAMES, keypoints=x,
                     confidence=conf)
    est = estimate_fits(det, cams, body, fit_iters=150, fps=30.0)
    assert est.kept == [10, 11] and est.report.frames_skipped == [12]
    assert list(est.motion.frame_index) == [10, 11]
    assert est.report.frames_detected == 2 and est.report.views_with_person == pytest.approx(2 / 3)
    assert est.report.mean_reprojection_px < 0.5 and est.report.views_rejected > 0
    assert est.report.fit_error_cm < 1.5 and est.report.keypoint_offsets
    own = estimate_fits(det, cams, body, fit_iters=150, fps=30.0, offsets=False)  # anny's own points: its keypoints
    assert not own.report.keypoint_offsets and own.report.fit_error_cm < est.report.fit_error_cm


# ---- errors without the capture extra ---------------------------------------------------------------------------
def test_missing_mediapipe_is_one_actionable_line(capture, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "mediapipe", None)  # import mediapipe -> ImportError, installed or not
    cap = tmp_path / "cap"
    shutil.copytree(capture.root, cap)
    (cap / "motion.npz").unlink()
    line = assert_one_line_error(_cli(str(cap), str(tmp_path / "proj")), tmp_path / "proj", "no body fits",
                           "pip install 'avatarctl[capture]'")
    assert "MediaPipe" in line
    shutil.rmtree(cap / "masks")
    shutil.rmtree(cap / "background")
    shutil.copy(capture.root / "motion.npz", cap / "motion.npz")
    assert_one_line_error(_cli(str(cap), str(tmp_path / "proj")), tmp_path / "proj", "background plate",
                    "pip install 'avatarctl[capture]'")
    assert_one_line_error(_cli(str(capture.root), str(tmp_path / "proj"), "--fits", "keypoints"), tmp_path / "proj",
                    "--fits keypoints", "avatarctl[capture]")
    assert_one_line_error(_cli(str(capture.root), str(tmp_path / "proj"), "--fits", "nope"), tmp_path / "proj", "--fits")
    assert_one_line_error(_cli(str(capture.root), str(tmp_path / "proj"), "--keypoint-silhouette", "-1"),
                          tmp_path / "proj", "--keypoint-silhouette", "0 to switch")
    assert_one_line_error(_cli(str(capture.root), str(tmp_path / "proj"), "--keypoint-outline", "nan"),
                          tmp_path / "proj", "--keypoint-outline", "0 to switch")


def test_fits_files_without_fits_names_the_fix(capture, tmp_path):
    cap = tmp_path / "cap"
    shutil.copytree(capture.root, cap)
    (cap / "motion.npz").unlink()
    assert_one_line_error(_cli(str(cap), str(tmp_path / "proj"), "--fits", "files"), tmp_path / "proj", "no body fits",
                    "--fits keypoints")


# ---- videos -------------------------------------------------------------------------------------------------------
def test_ingest_from_per_camera_videos(capture, tmp_path):
    import cv2
    import imageio_ffmpeg

    from avatarctl.io.project_io import load_project_capture
    from avatarctl.project import Project, hash_tree

    cap = tmp_path / "cap"
    shutil.copytree(capture.root, cap, ignore=shutil.ignore_patterns("images"))
    (cap / "videos").mkdir()
    for c in capture.cameras:
        frames = [cv2.imread(str(capture.root / "images" / c.name / f"{f:06d}.jpg"))[..., ::-1]
                  for f in capture.frames]
        h, w = frames[0].shape[:2]
        writer = imageio_ffmpeg.write_frames(str(cap / "videos" / f"{c.name}.mp4"), (w, h), fps=10, quality=10,
                                             macro_block_size=1)
        writer.send(None)
        for fr in frames:
            writer.send(np.ascontiguousarray(fr))
        writer.close()
    before = hash_tree(cap)
    proj = tmp_path / "proj"
    res = _cli(str(cap), str(proj), "--frames", "1:4", "--no-contact-sheet")
    assert res.exit_code == 0, res.output
    pc = load_project_capture(Project.open(proj))
    assert sorted(pc.frames) == [1, 2, 3]
    ref = cv2.imread(str(capture.root / "images" / capture.cameras[0].name / "000002.jpg")).astype(np.float64)
    got = cv2.imread(str(proj / "ingest" / "frames" / capture.cameras[0].name / "000002.jpg")).astype(np.float64)
    psnr = 10 * np.log10(255 ** 2 / ((ref - got) ** 2).mean())
    assert psnr > 28, psnr  # the right frame, decoded (lossy mp4)
    assert hash_tree(cap) == before  # the capture is only read


# ---- with MediaPipe: the whole own-capture path on a synth capture -------------------------------------------------
@pytest.mark.slow
def test_estimated_masks_and_fits_on_synth(tmp_path):
    pytest.importorskip("mediapipe")
    synth = pytest.importorskip("avatarctl.synth")

    full = tmp_path / "full"
    synth.synthesize(full, synth.SynthConfig.preset("micro", seed=0, size=128))  # at 64 px MediaPipe finds nobody
    cap = tmp_path / "cap"
    cap.mkdir()
    for n in ("intri.yml", "extri.yml", "images"):
        (shutil.copytree if (full / n).is_dir() else shutil.copy)(full / n, cap / n)
    res = _cli(str(cap), str(tmp_path / "proj"), "--keypoint-fit-iters", "100")
    assert res.exit_code == 0, res.output
    summary = json.loads((tmp_path / "proj" / "project.json").read_text())["stages"][0]["summary"]
    assert summary["masks"] == "mediapipe" and summary["fits"] == "keypoints"
    assert summary["estimate"]["frames_detected"] > 0 and summary["estimate"]["keypoint_offsets"] is True
    refined = summary["estimate"]["masks_refined"]  # against plates estimated from the frames (static cameras)
    assert refined is not None and min(refined["plate_known"].values()) > 0.5
    assert summary["vertices_inside_masks"] > 0.8
    from avatarctl.ingest.estimate import Detections

    det = Detections.load(tmp_path / "proj" / "ingest" / "keypoints.npz")  # what the detector found, kept
    assert det.keypoints.shape[:2] == (len(det.frames), len(det.cams)) and np.isfinite(det.keypoints).any()


# ---- the keypoint fit's silhouette term -------------------------------------------------------------------------
def test_mask_distance_is_zero_inside_and_grows_outside():
    from avatarctl.body.fit_keypoints import field_grid, mask_distance

    m = np.zeros((40, 60), dtype=bool)
    m[10:30, 20:40] = True
    d = mask_distance(m, (40, 60))
    assert d.dtype == np.float32 and (d[m] == 0).all()
    assert d[20, 45] == pytest.approx(6.0, abs=0.05) and d[20, 5] == pytest.approx(15.0, abs=0.05)
    assert d[2, 5] == pytest.approx(np.hypot(15, 8), abs=0.1)  # Euclidean, not city-block
    half = mask_distance(m, (20, 30))  # resized: values stay in the mask's own pixels
    assert half[10, 27] == pytest.approx(d[20:22, 54:56].mean(), abs=0.01)
    assert field_grid(512, 256) == (64, 128) and field_grid(96, 96) == (96, 96)
    with pytest.raises(ValueError, match="empty mask"):
        mask_distance(np.zeros((4, 4), bool), (4, 4))


def test_silhouette_term_penalises_only_points_outside_in_metres():
    import torch

    from avatarctl.body.fit_keypoints import SilhouetteTargets, SilhouetteTerm, mask_distance
    from avatarctl.geometry.triangulate import projection_matrices

    cam = ring_cameras(1, 128)[0].pinhole()
    mask = np.zeros((128, 128), dtype=bool)
    mask[32:96, 32:96] = True
    sil = SilhouetteTargets(P=projection_matrices([cam]), image_size=np.array([[128.0, 128.0]]),
                            focal_px=np.array([cam.K[0, 0]]), distance=mask_distance(mask, (128, 128))[None, None],
                            weight=np.ones((1, 1)))
    term = SilhouetteTerm(sil, frames=1, dtype=torch.float64)
    # points on the ray through a pixel: the centre (inside) and 20 px right of the mask (outside)
    Kinv, R = np.linalg.inv(cam.K), cam.R
    pts = []
    for u, v in ((64.0, 64.0), (115.0, 64.0)):
        ray = R.T @ (Kinv @ np.array([u, v, 1.0]))
        pts.append(cam.center + ray * (2.0 / (R @ ray)[2]))  # at depth 2 m
    V = torch.tensor(np.stack(pts)[None], dtype=torch.float64, requires_grad=True)
    r, d_px = term.distances(V)
    assert d_px[0, 0, 0] == 0 and d_px[0, 0, 1].item() == pytest.approx(115 - 95.5, abs=0.6)
    assert r[0, 0, 1].item() == pytest.approx(d_px[0, 0, 1].item() * 2.0 / cam.K[0, 0], rel=1e-3)  # metres
    term.loss(V, 0.05).backward()
    assert V.grad[0, 0].abs().max() == 0  # inside: no pull at all (one-sided)
    uv_step = cam.K[:2, :2] @ (cam.R @ V.grad[0, 1].numpy())[:2]  # the gradient's direction in the image
    assert uv_step[0] > 0 and abs(uv_step[1]) < 1e-3 * abs(uv_step[0])  # descent moves the point left, inwards
    assert term.inside(V.detach()) == pytest.approx(0.5)


def test_outline_term_pulls_the_nearest_projected_point_out_to_the_masks_outline():
    """The silhouette term's other side: the outline points of a square mask pull the nearest projected point out
    to them (the one-sided term has nothing to say about points inside the mask), in metres at its depth."""
    import torch

    from avatarctl.body.fit_keypoints import SilhouetteTargets, SilhouetteTerm, mask_distance, outline_points
    from avatarctl.geometry.triangulate import projection_matrices

    cam = ring_cameras(1, 128)[0].pinhole()
    mask = np.zeros((128, 128), dtype=bool)
    mask[32:96, 32:96] = True
    field = mask_distance(mask, (64, 64))  # the field's grid at half the image's size
    pts = outline_points(field, np.array([128.0, 128.0]), n=1000)
    assert len(pts) == 4 * 31  # the boundary pixels of a 32 x 32 square on the grid
    assert pts.min() == pytest.approx(32.5, abs=1e-4) and pts.max() == pytest.approx(94.5, abs=1e-4)
    assert len(outline_points(np.ones((8, 8), np.float32), np.array([16.0, 16.0]))) == 0  # an empty mask
    sil = SilhouetteTargets(P=projection_matrices([cam]), image_size=np.array([[128.0, 128.0]]),
                            focal_px=np.array([cam.K[0, 0]]), distance=field[None, None], weight=np.ones((1, 1)))
    term = SilhouetteTerm(sil, frames=1, dtype=torch.float64)
    Kinv, R = np.linalg.inv(cam.K), cam.R

    def at(u, v):  # the point at depth 2 m on the ray through pixel (u, v)
        ray = R.T @ (Kinv @ np.array([u, v, 1.0]))
        return cam.center + ray * (2.0 / (R @ ray)[2])

    # two points inside the mask: the centre and one 10 px left of its right edge (nearest to the right edge)
    V = torch.tensor(np.stack([at(64.0, 64.0), at(84.5, 64.0)])[None], dtype=torch.float64, requires_grad=True)
    assert term.loss(V, 0.05).item() == 0  # inside: the one-sided term is silent
    d = term.outline_distances(V)  # [1, 1, points] metres from each outline point to the nearer point
    right = torch.as_tensor((pts[:, 0] > 94) & (np.abs(pts[:, 1] - 64) < 2))
    assert d[0, 0, :len(pts)][right].min().item() == pytest.approx(10.0 * 2.0 / cam.K[0, 0], rel=0.02)
    term.outline_loss(V, 0.05).backward()
    uv_step = cam.K[:2, :2] @ (cam.R @ V.grad[0, 1].numpy())[:2]
    assert uv_step[0] < 0  # descent moves the point right, out to the outline
    assert term.outline_mean(V.detach()) > 0


def test_outline_term_places_an_unobserved_arm_from_one_view():
    """Keypoints without the left arm's elbow and wrist, one camera and the true silhouette: the arm raised beside the
    torso. The one-sided term leaves it where the keypoint fit put it, the outline term pulls it out to the mask;
    its gate keeps it off when the outline lies further from the body than `outline_gate_m` (loose clothing)."""
    import torch

    from avatarctl.body.anny_model import AnnyBody
    from avatarctl.body.fit_keypoints import (FIT_BONES, AnnyKeypoints, KeypointFitConfig, KeypointTargets,
                                              fit_keypoints)
    from avatarctl.ingest.estimate import silhouette_targets
    from avatarctl.ingest.keypoints import KEYPOINT_NAMES
    from avatarctl.geometry.silhouette import rasterize_silhouette

    body = AnnyBody()
    kp = AnnyKeypoints(body, KEYPOINT_NAMES)
    cams = [ring_cameras(4, 128)[0].pinhole()]
    rot = torch.zeros(1, len(FIT_BONES), 3, dtype=torch.float64)
    rot[0, FIT_BONES.index("upperarm01.L")] = torch.tensor(ARM_RAISE, dtype=torch.float64)
    pose = kp.pose_matrices(rot, torch.eye(3, dtype=torch.float64)[None], torch.zeros(1, 3, dtype=torch.float64))
    pheno = torch.full((6,), 0.5, dtype=torch.float64)
    with torch.no_grad():
        K, V = kp(pose, pheno)
    faces = body.faces().cpu().numpy()
    masks = {(cams[0].name, 0): rasterize_silhouette(cams[0], V[0].numpy(), faces)}
    arm = [i for i, n in enumerate(KEYPOINT_NAMES) if n in ("left_elbow", "left_wrist")]
    w = np.ones(K.shape[:2])
    w[:, arm] = 0.0
    targets = KeypointTargets(KEYPOINT_NAMES, K.numpy(), w)
    sil = silhouette_targets(cams, [cams[0].name], [0], lambda c, f: masks[(c, f)])
    errs = {}
    for w_out, gate in ((0.0, 0.1), (30.0, 0.1), (30.0, 0.025)):
        cfg = KeypointFitConfig(iters=200, fit_shape=False, w_silhouette=100.0, w_outline=w_out,
                                silhouette_start=0.25, outline_gate_m=gate)
        fit = fit_keypoints(kp, targets, cfg, silhouettes=sil)
        with torch.no_grad():
            K2, _ = kp(torch.as_tensor(fit.motion.pose_parameters, dtype=torch.float64), pheno)
        errs[w_out, gate] = (K2 - K)[:, arm].norm(dim=-1).mean().item()
        if w_out:  # the outline 3.7 cm from the body at s_0: on under a 10 cm gate, off under 2.5 cm
            assert fit.silhouette.outline_on == (gate > 0.037)
        else:
            assert np.isnan(fit.silhouette.outline_after_m) and not fit.silhouette.outline_on
    assert fit.silhouette.outline_before_m == pytest.approx(0.037, abs=0.002)
    assert errs[30.0, 0.1] < 0.3 * errs[0.0, 0.1], errs  # measured 29.5 cm -> 3.5 cm
    assert errs[30.0, 0.025] == errs[0.0, 0.1]  # gated off: the fit without the term


def test_silhouette_term_recovers_unobserved_legs():
    """Keypoints of the upper body only (legs unobserved) + the true silhouettes in six views: the fit with the term
    finds the flexed legs (the keypoint-only fit leaves them in the reference pose) and more of the body projects
    inside the masks."""
    import roma
    import torch

    from avatarctl.body.anny_model import AnnyBody
    from avatarctl.body.fit_keypoints import (FIT_BONES, AnnyKeypoints, KeypointFitConfig, KeypointTargets,
                                              fit_keypoints)
    from avatarctl.ingest.estimate import silhouette_targets
    from avatarctl.ingest.keypoints import KEYPOINT_NAMES
    from avatarctl.geometry.silhouette import rasterize_silhouette

    body = AnnyBody()
    kp = AnnyKeypoints(body, KEYPOINT_NAMES)
    cams = [c.pinhole() for c in ring_cameras(6, 128)]
    rot = torch.zeros(2, len(FIT_BONES), 3, dtype=torch.float64)
    rot[:, FIT_BONES.index("upperleg01.L"), 0] = torch.tensor([-0.7, -0.5], dtype=torch.float64)  # hip flexion
    rot[:, FIT_BONES.index("lowerleg01.L"), 0] = torch.tensor([0.8, 0.6], dtype=torch.float64)  # knee flexion
    rot[:, FIT_BONES.index("upperleg01.R"), 0] = torch.tensor([0.3, 0.4], dtype=torch.float64)
    pose = kp.pose_matrices(rot, torch.eye(3, dtype=torch.float64).expand(2, 3, 3), torch.zeros(2, 3, dtype=torch.float64))
    pheno = torch.full((6,), 0.5, dtype=torch.float64)
    with torch.no_grad():
        K, V = kp(pose, pheno)
    faces = body.faces().cpu().numpy()
    masks = {(c.name, f): rasterize_silhouette(c, V[f].numpy(), faces) for c in cams for f in (0, 1)}
    legs = [i for i, n in enumerate(KEYPOINT_NAMES) if any(p in n for p in ("knee", "ankle", "heel", "toe"))]
    w = np.ones(K.shape[:2])
    w[:, legs] = 0.0
    targets = KeypointTargets(KEYPOINT_NAMES, K.numpy(), w)
    sil = silhouette_targets(cams, [c.name for c in cams], [0, 1], lambda c, f: masks[(c, f)])
    errs = {}
    for weight in (0.0, 100.0):
        cfg = KeypointFitConfig(iters=200, fit_shape=False, w_silhouette=weight, silhouette_start=0.25)
        fit = fit_keypoints(kp, targets, cfg, silhouettes=sil)
        with torch.no_grad():
            K2, _ = kp(torch.as_tensor(fit.motion.pose_parameters, dtype=torch.float64), pheno)
        errs[weight] = (K2 - K)[:, legs].norm(dim=-1).mean().item()
        if weight:
            assert fit.silhouette is not None and fit.silhouette.inside_after > fit.silhouette.inside_before + 0.02
        else:
            assert fit.silhouette is None
    assert errs[100.0] < 0.5 * errs[0.0], errs  # measured 12.6 cm -> 0.9 cm


def test_each_cameras_detector_is_primed_on_the_next_frames_backwards(monkeypatch):
    """`detect_people` feeds each camera's video-mode detector frames WARMUP_FRAMES..1 (backwards) before the pass
    from the first frame, and keeps only the pass's results (cold, MediaPipe drops parts of the person on the first
    frames: docs/own_capture.md)."""
    from avatarctl.ingest import estimate, keypoints

    calls: list[tuple[int, int]] = []  # (detector, frame)

    class FakeDetector:
        made = 0

        def __init__(self, masks: bool = True, **kw):
            FakeDetector.made += 1
            self.id = FakeDetector.made

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return None

        def __call__(self, rgb):
            f = int(rgb[0, 0, 0])
            calls.append((self.id, f))
            J = len(keypoints.KEYPOINT_NAMES)
            return keypoints.PersonDetection(keypoints=np.full((J, 2), float(f)), confidence=np.ones(J),
                                             mask=np.full((4, 4), f % 2 == 0))

    monkeypatch.setattr(keypoints, "PoseDetector", FakeDetector)
    frames = list(range(10, 18))
    # images of 256 px (masks alternately full and empty: odd, but not small images, so no second pass)
    det = estimate.detect_people(lambda c, f: np.full((256, 256, 3), f, np.uint8), ["a", "b"], frames, masks=True)
    warm = frames[estimate.WARMUP_FRAMES:0:-1]
    assert warm == [15, 14, 13, 12, 11]
    assert calls == [(1, f) for f in warm + frames] + [(2, f) for f in warm + frames]
    assert np.array_equal(det.keypoints[:, 0, 0, 0], frames)  # the pass's results, in frame order
    assert det.mask("b", 12).all() and not det.mask("b", 13).any()
    short = estimate.detect_people(lambda c, f: np.full((4, 4, 3), f, np.uint8), ["a"], [3], masks=False)
    assert calls[-1] == (3, 3) and short.keypoints.shape[0] == 1  # one frame: nothing to prime on


def test_a_small_cameras_odd_masks_are_detected_again_on_enlarged_images(monkeypatch):
    """At 128 px MediaPipe's tracker can lose the person for a stretch of frames (its masks the floor); a camera of
    small images whose mask areas are odd runs again on images enlarged to DETECT_MIN_SIDE, and each odd frame takes
    that run's detection where its mask area is not odd (`ingest.keypoints`, "Small images")."""
    from avatarctl.ingest import estimate, keypoints

    made: list[tuple[str, float]] = []
    J = len(keypoints.KEYPOINT_NAMES)

    class FakeDetector:
        def __init__(self, masks: bool = True, scale: float = 1.0, **kw):
            self.scale = scale

        def __enter__(self):
            made.append((self.cam, self.scale))
            return self

        def __exit__(self, *exc):
            return None

        def __call__(self, rgb):
            cam, f = int(rgb[0, 0, 1]), int(rgb[0, 0, 0])
            H, W = rgb.shape[:2]
            mask = np.zeros((H, W), bool)
            lost = cam == 0 and f < 2 and self.scale == 1.0 or cam == 0 and f == 5  # frame 5: lost in both runs
            if lost:
                mask[:] = True  # the floor: the whole image
            else:
                mask[10:30, 10:30] = True
            tag = 100.0 * (self.scale != 1.0)
            return keypoints.PersonDetection(keypoints=np.full((J, 2), tag + f), confidence=np.ones(J), mask=mask)

    FakeDetector.cam = "?"
    monkeypatch.setattr(keypoints, "PoseDetector", FakeDetector)

    def read(c, f, size=64):
        FakeDetector.cam = c
        img = np.zeros((size, size, 3), np.uint8)
        img[..., 0], img[..., 1] = f, int(c[-1])
        return img

    frames = list(range(8))
    det = estimate.detect_people(read, ["c0", "c1"], frames, masks=True)
    assert [s for _, s in made] == [1.0, keypoints.DETECT_MIN_SIDE / 64, 1.0]  # c0 twice, c1 (no odd mask) once
    src = det.keypoints[:, 0, 0, 0]
    assert np.array_equal(src, [100, 101, 2, 3, 4, 5, 6, 7])  # frames 0-1 mended; 5 odd in both runs: kept
    assert det.mask("c0", 0).sum() == 400 and det.mask("c0", 5).all()
    assert np.array_equal(det.keypoints[:, 1, 0, 0], frames)
    assert det.enlarged == {"c0": [0, 1]}
    nan = float("nan")
    report = estimate.EstimateReport(frames_detected=8, frames_total=8, views_with_person=1.0, frames_skipped=[],
                                     mean_reprojection_px=nan, views_rejected=nan, keypoints_triangulated=nan,
                                     fit_error_cm=nan, fit_seconds=0.0, detected_enlarged=det.enlarged)
    row = dict(report.rows(fitted=False))["detected again"]
    assert row.startswith("c0 (2 frames)") and f"{keypoints.DETECT_MIN_SIDE} px" in row
    assert report.to_json()["detected_enlarged"] == {"c0": [0, 1]}
    made.clear()
    estimate.detect_people(lambda c, f: read(c, f, size=256), ["c0"], frames, masks=True)
    assert [s for _, s in made] == [1.0]  # images of 256 px: the odd masks stay as found
    assert np.array_equal(estimate.odd_masks(np.array([4.0, 6.0, 0.0, 10.0])), [False, False, True, True])
