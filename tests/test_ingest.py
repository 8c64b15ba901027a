"""`avatarctl ingest` on a generated EasyMocap capture (anny body): outputs, undistortion, masks, selection,
the capture left untouched, and one test per validation error (one line, exit 2, nothing written)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from avatarctl.cli.app import app
from avatarctl.project import hash_tree, sha256_file
from fixtures.captures import RenderedCapture, make_easymocap_capture
from fixtures.cli_errors import assert_one_line_error

pytestmark = pytest.mark.anny


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> RenderedCapture:
    return make_easymocap_capture(tmp_path_factory.mktemp("cap") / "cap", frames=[0, 1, 2, 3, 4, 5], n_cams=4)


@pytest.fixture(scope="module")
def ingested(capture, tmp_path_factory):
    before = {p.relative_to(capture.root): sha256_file(p) for p in capture.root.rglob("*") if p.is_file()}
    proj = tmp_path_factory.mktemp("proj") / "proj"
    res = CliRunner().invoke(app, ["ingest", str(capture.root), str(proj)])
    assert res.exit_code == 0, res.output
    return proj, res.output, before


def copy_capture(capture: RenderedCapture, tmp_path: Path) -> Path:
    dst = tmp_path / "cap"
    shutil.copytree(capture.root, dst)
    return dst


def ingest_cli(*args: str):
    return CliRunner().invoke(app, ["ingest", *args])


# ---- the happy path -------------------------------------------------------------------------------------------
def test_ingest_writes_the_project_contract(capture, ingested):
    from avatarctl.io.project_io import load_project_capture
    from avatarctl.project import Project

    proj, out, _ = ingested
    assert "detected format easymocap" in out
    pc = load_project_capture(Project.open(proj))
    assert sorted(pc.cameras) == ["00", "01", "02", "03"]
    for cam in capture.cameras:
        got = pc.cameras[cam.name]
        assert got.is_pinhole and np.allclose(got.K, cam.K) and np.allclose(got.R, cam.R) and np.allclose(got.T, cam.T)
    assert pc.frames == capture.frames
    np.testing.assert_allclose(pc.motion.pose_parameters, capture.motion.pose_parameters, atol=1e-6)
    m = Project.open(proj).manifest
    assert m.body_model.to_json() == {"name": "anny", "path": None}
    assert m.source.format == "easymocap" and m.source.sha256 == hash_tree(capture.root)[0]
    assert m.source.files == sum(1 for p in capture.root.rglob("*") if p.is_file())
    rec = m.stages[-1]
    assert rec.summary["vertices_inside_masks"] >= 0.99
    assert (proj / "ingest" / "contact_sheet.png").is_file()
    # default split: every 4th view tests, first 2/3 of the frames train
    assert pc.split.test_views == ["03"] and pc.split.train_views == ["00", "01", "02"]
    assert pc.split.train_frames == [0, 1, 2, 3] and pc.split.test_frames == [4, 5]


def test_frames_and_masks_match_undistorted_ground_truth(capture, ingested):
    import cv2

    from avatarctl.ingest.masks import iou
    from avatarctl.io.project_io import read_frame, read_mask
    from avatarctl.project import Project

    proj, _, _ = ingested
    p = Project.open(proj)
    for cam in capture.cameras[:2]:
        for f in (0, 5):
            raw = cv2.imread(str(capture.root / "images" / cam.name / f"{f:06d}.jpg"))[..., ::-1]
            want = cv2.undistort(raw, cam.K, cam.dist, None, cam.K)
            got = read_frame(p, cam.name, f)
            mse = ((got.astype(float) - want.astype(float))[4:-4, 4:-4] ** 2).mean()
            psnr = 10 * np.log10(255.0 ** 2 / mse)
            assert psnr > 28.0, (cam.name, f, psnr)  # JPEG re-encoding: ~30 dB; a 1-px shift: < 25 dB
            # the undistorted mask agrees with the mesh rendered directly in the pinhole camera
            from avatarctl.geometry.silhouette import rasterize_silhouette

            gt = rasterize_silhouette(cam.pinhole(), capture.vertices[f], capture.faces)
            assert iou(read_mask(p, cam.name, f), gt) > 0.9


def test_capture_is_not_modified(capture, ingested):
    _, _, before = ingested
    after = {p.relative_to(capture.root): sha256_file(p) for p in capture.root.rglob("*") if p.is_file()}
    assert after == before


def test_background_masks_match_ground_truth(capture, tmp_path):
    from avatarctl.ingest.masks import iou
    from avatarctl.io.project_io import read_mask
    from avatarctl.project import Project

    cap = copy_capture(capture, tmp_path)
    shutil.rmtree(cap / "masks")
    proj = tmp_path / "proj"
    res = ingest_cli(str(cap), str(proj), "--masks", "background", "--frames", "0,3", "--no-contact-sheet")
    assert res.exit_code == 0, res.output
    p = Project.open(proj)
    assert p.manifest.stages[-1].summary["masks"] == "background"
    ious = []
    for cam in capture.cameras:
        for f in (0, 3):
            from avatarctl.geometry.silhouette import rasterize_silhouette

            gt = rasterize_silhouette(cam.pinhole(), capture.vertices[f], capture.faces)
            ious.append(iou(read_mask(p, cam.name, f), gt))
    assert min(ious) > 0.9 and np.mean(ious) > 0.94, ious


def test_frames_views_resize_selection(capture, tmp_path):
    from avatarctl.io.project_io import load_project_capture
    from avatarctl.project import Project

    proj = tmp_path / "proj"
    res = ingest_cli(str(capture.root), str(proj), "--frames", "1:6:2", "--views", "02,00", "--resize", "0.5",
                     "--no-contact-sheet")
    assert res.exit_code == 0, res.output
    pc = load_project_capture(Project.open(proj))
    assert pc.frames == [1, 3, 5] and sorted(pc.cameras) == ["00", "02"]
    cam = pc.cameras["00"]
    assert (cam.width, cam.height) == (64, 64)
    np.testing.assert_allclose(cam.K, capture.cameras[0].pinhole().scaled(0.5).K)
    assert pc.image("00", 3).shape == (64, 64, 3) and pc.mask("00", 3).shape == (64, 64)
    assert not (proj / "ingest" / "contact_sheet.png").exists()


def test_capture_split_json_is_used(capture, tmp_path):
    from avatarctl.io.project_io import load_split

    cap = copy_capture(capture, tmp_path)
    (cap / "split.json").write_text(json.dumps({"train_frames": [0, 2, 4], "test_frames": [1, 3, 5],
                                                "train_views": ["00", "02"], "test_views": ["01", "03"]}))
    proj = tmp_path / "proj"
    res = ingest_cli(str(cap), str(proj), "--frames", "0:4", "--no-contact-sheet")
    assert res.exit_code == 0, res.output
    s = load_split(proj / "ingest" / "split.json")
    assert s.train_frames == [0, 2] and s.test_frames == [1, 3] and s.test_views == ["01", "03"]


def test_default_split_rules():
    from avatarctl.ingest.split import default_split

    s = default_split(list(range(9)), [f"c{i}" for i in range(8)])
    assert s.test_views == ["c3", "c7"] and len(s.train_views) == 6
    assert s.train_frames == list(range(6)) and s.test_frames == [6, 7, 8]
    mono = default_split([0, 1, 2], ["cam0"])
    assert mono.train_views == ["cam0"] and mono.test_views == ["cam0"]


# ---- validation errors: one line, exit 2, nothing written -------------------------------------------------------
def test_error_existing_project_is_refused(capture, tmp_path):
    proj = tmp_path / "proj"
    proj.mkdir()
    (proj / "keep.txt").write_text("mine")
    res = ingest_cli(str(capture.root), str(proj))
    assert res.exit_code == 2 and "not empty" in res.output
    assert (proj / "keep.txt").read_text() == "mine" and len(list(proj.iterdir())) == 1


def test_error_unknown_format(tmp_path):
    cap = tmp_path / "cap"
    cap.mkdir()
    (cap / "video.mov").write_bytes(b"x")
    assert_one_line_error(ingest_cli(str(cap), str(tmp_path / "proj")), tmp_path / "proj", "unknown capture format")


def test_error_missing_camera(capture, tmp_path):
    cap = copy_capture(capture, tmp_path)
    shutil.rmtree(cap / "images" / "01")
    assert_one_line_error(ingest_cli(str(cap), str(tmp_path / "proj")), tmp_path / "proj", "camera 01 has no images")


def test_error_extra_camera(capture, tmp_path):
    cap = copy_capture(capture, tmp_path)
    shutil.copytree(cap / "images" / "00", cap / "images" / "99")
    line = assert_one_line_error(ingest_cli(str(cap), str(tmp_path / "proj")), tmp_path / "proj", "extra cameras", "99")
    assert "--views" in line
    # choosing the calibrated cameras works
    res = ingest_cli(str(cap), str(tmp_path / "proj2"), "--views", "00,01", "--frames", "0", "--no-contact-sheet")
    assert res.exit_code == 0, res.output


def test_error_image_count_mismatch(capture, tmp_path):
    cap = copy_capture(capture, tmp_path)
    (cap / "images" / "02" / "000004.jpg").unlink()
    assert_one_line_error(ingest_cli(str(cap), str(tmp_path / "proj")), tmp_path / "proj",
                          "frame-count mismatch", "camera 02", "4")


def test_error_mask_count_mismatch(capture, tmp_path):
    cap = copy_capture(capture, tmp_path)
    (cap / "masks" / "01" / "000002.png").unlink()
    assert_one_line_error(ingest_cli(str(cap), str(tmp_path / "proj")), tmp_path / "proj",
                          "frame-count mismatch", "masks", "camera 01")


def test_error_fits_count_mismatch(capture, tmp_path):
    cap = copy_capture(capture, tmp_path)
    capture.motion.select(slice(0, 4)).save(cap / "motion.npz")
    assert_one_line_error(ingest_cli(str(cap), str(tmp_path / "proj")), tmp_path / "proj",
                          "frame-count mismatch", "body fits", "4, 5")


def test_error_corrupt_image(capture, tmp_path):
    cap = copy_capture(capture, tmp_path)
    bad = cap / "images" / "03" / "000005.jpg"
    bad.write_bytes(b"\xff\xd8\xff\xe0 this is not a jpeg")
    assert_one_line_error(ingest_cli(str(cap), str(tmp_path / "proj")), tmp_path / "proj",
                          "corrupt", "000005.jpg")


def test_error_non_finite_poses(capture, tmp_path):
    cap = copy_capture(capture, tmp_path)
    d = capture.motion.to_npz_dict()
    d["pose_parameters"] = d["pose_parameters"].copy()
    d["pose_parameters"][2, 5, 0, 0] = np.nan
    np.savez(cap / "motion.npz", **d)
    assert_one_line_error(ingest_cli(str(cap), str(tmp_path / "proj")), tmp_path / "proj", "non-finite",
                          "motion.npz")


def test_error_wrong_shape_poses(capture, tmp_path):
    cap = copy_capture(capture, tmp_path)
    d = capture.motion.to_npz_dict()
    d["pose_parameters"] = d["pose_parameters"][:, :100]
    np.savez(cap / "motion.npz", **d)
    assert_one_line_error(ingest_cli(str(cap), str(tmp_path / "proj")), tmp_path / "proj", "[frames, 104, 4, 4]")


def test_error_camera_translation_in_millimetres(capture, tmp_path):
    from dataclasses import replace

    from avatarctl.io.easymocap import write_easymocap_cameras

    cap = copy_capture(capture, tmp_path)
    write_easymocap_cameras(cap, [replace(c, T=c.T * 1000) for c in capture.cameras])
    assert_one_line_error(ingest_cli(str(cap), str(tmp_path / "proj")), tmp_path / "proj", "millimetres", "camera 00")


def test_error_body_translation_in_millimetres(capture, tmp_path):
    cap = copy_capture(capture, tmp_path)
    d = capture.motion.to_npz_dict()
    d["pose_parameters"] = d["pose_parameters"].copy()
    d["pose_parameters"][:, 0, :3, 3] = [[0.0, 0.0, 900.0]]
    np.savez(cap / "motion.npz", **d)
    assert_one_line_error(ingest_cli(str(cap), str(tmp_path / "proj")), tmp_path / "proj", "millimetres", "motion.npz")


def test_error_empty_mask(capture, tmp_path):
    import cv2

    cap = copy_capture(capture, tmp_path)
    cv2.imwrite(str(cap / "masks" / "02" / "000001.png"), np.zeros((128, 128), np.uint8))
    assert_one_line_error(ingest_cli(str(cap), str(tmp_path / "proj")), tmp_path / "proj",
                          "empty mask", "camera 02, frame 1")


def test_error_no_masks_and_no_background(capture, tmp_path, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "mediapipe", None)  # without the capture extra: masks cannot be estimated
    cap = copy_capture(capture, tmp_path)
    shutil.rmtree(cap / "masks")
    shutil.rmtree(cap / "background")
    assert_one_line_error(ingest_cli(str(cap), str(tmp_path / "proj")), tmp_path / "proj", "background plate")


def test_error_smpl_fits_without_model_file(capture, tmp_path):
    cap = copy_capture(capture, tmp_path)
    (cap / "motion.npz").unlink()
    (cap / "smpl").mkdir()
    for f in capture.frames:
        (cap / "smpl" / f"{f:06d}.json").write_text(json.dumps(
            [{"id": 0, "Rh": [[0, 0, 0]], "Th": [[0, 0, 0]], "poses": [[0.0] * 72], "shapes": [[0.0] * 10]}]))
    assert_one_line_error(ingest_cli(str(cap), str(tmp_path / "proj")), tmp_path / "proj", "smpl",
                          "--body-model-path")
    assert_one_line_error(ingest_cli(str(cap), str(tmp_path / "proj"), "--body-model-path", str(tmp_path / "nope.pkl")),
                          tmp_path / "proj", "model file not found")
    assert_one_line_error(ingest_cli(str(cap), str(tmp_path / "proj"), "--body-model", "anny"), tmp_path / "proj",
                          "fits are for smpl")


def test_error_bad_options(capture, tmp_path):
    assert_one_line_error(ingest_cli(str(capture.root), str(tmp_path / "proj"), "--frames", "a:b"),
                          tmp_path / "proj", "--frames")
    assert_one_line_error(ingest_cli(str(capture.root), str(tmp_path / "proj"), "--views", "00,77"),
                          tmp_path / "proj", "unknown cameras")
    assert_one_line_error(ingest_cli(str(capture.root), str(tmp_path / "proj"), "--resize", "0"),
                          tmp_path / "proj", "--resize")
