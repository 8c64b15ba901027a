"""4D-DRESS (`avatarctl.io.four_d_dress`) on a synthetic take in the release's exact layout
(`fixtures.dataset_layouts`): detection, the quirks (3x4 world -> camera extrinsics, `capture-f%05d.png` numbering,
image frames that are not scan frames, SMPL-X preferred over SMPL, pickles through the restricted unpickler), the
labelled scans as ground-truth geometry, one-line errors, and ingest -> micro fit -> eval --region garment."""

from __future__ import annotations

import os
import pickle
import shutil

import numpy as np
import pytest
from fixtures.dataset_layouts import FOUR_D_DRESS_CAMERAS, make_four_d_dress_take

from avatarctl.errors import InputError


@pytest.fixture(scope="module")
def take(random_smplx, tmp_path_factory):
    return make_four_d_dress_take(tmp_path_factory.mktemp("4dd") / "00170" / "Inner" / "Take1", random_smplx[1])


def test_reader_reads_the_release_layout(take):
    from avatarctl.io.detect import detect_format
    from avatarctl.io.four_d_dress import read_four_d_dress

    fmt, reason = detect_format(take.root)
    assert fmt == "4d_dress" and "cameras.pkl" in reason
    src = read_four_d_dress(take.root)
    assert src.camera_names == list(FOUR_D_DRESS_CAMERAS) and src.sequence == "00170/Inner/Take1"
    for got, want in zip(src.cameras, take.cameras):
        np.testing.assert_allclose(got.R, want.R, atol=1e-6)
        np.testing.assert_allclose(got.T, want.T, atol=1e-6)
        np.testing.assert_allclose(got.K, want.K, atol=1e-9)
        assert (got.width, got.height) == (36, 48) and not got.dist.any()  # portrait, no distortion
    # frame 15 has images but is not a scan frame (basic_info.pkl): left out, and said so
    assert src.image_frames == {n: {11, 12, 13, 14} for n in FOUR_D_DRESS_CAMERAS}
    assert src.mask_frames == src.image_frames and any("15" in n for n in src.notes)
    assert src.images.where("0028", 12).endswith("Capture/0028/images/capture-f00012.png")
    fits = src.fits
    assert fits.body_model == "smplx" and list(fits.frame_index) == [11, 12, 13, 14]
    for key in ("global_orient", "body_pose", "transl", "left_hand_pose", "expression"):
        np.testing.assert_allclose(getattr(fits, key), getattr(take.motion, key), atol=1e-6, err_msg=key)


def test_the_recording_is_named_by_its_folders(tmp_path):
    from avatarctl.io.four_d_dress import sequence_name

    for path, want in (("00170/Inner/Take1", "00170/Inner/Take1"), ("00170_Inner/Inner/Take5", "00170/Inner/Take5"),
                       ("00185/Outer/Take12", "00185/Outer/Take12"), ("my_take", ""), ("00170/Inner/take1", ""),
                       ("0170/Inner/Take1", "")):
        (tmp_path / path).mkdir(parents=True, exist_ok=True)
        assert sequence_name(tmp_path / path) == want, path


def test_smpl_fits_when_the_take_has_no_smplx(take, tmp_path):
    from avatarctl.io.four_d_dress import read_four_d_dress

    copy = tmp_path / "Take1"
    shutil.copytree(take.root, copy, ignore=shutil.ignore_patterns("SMPLX"))
    src = read_four_d_dress(copy)
    assert src.fits.body_model == "smpl" and src.fits.body_pose.shape == (4, 69)
    (copy / "SMPL" / "mesh-f00013_smpl.pkl").write_bytes(pickle.dumps({"global_orient": np.zeros(3)}))
    with pytest.raises(InputError, match="fit has no 'body_pose'"):
        read_four_d_dress(copy)


def test_pickles_are_read_without_running_code(take, tmp_path):
    from avatarctl.io.four_d_dress import read_four_d_dress

    copy = tmp_path / "Take1"
    shutil.copytree(take.root, copy)
    marker = tmp_path / "pwned"

    class Payload:
        def __reduce__(self):
            return os.system, (f"touch {marker}",)

    (copy / "Capture" / "cameras.pkl").write_bytes(pickle.dumps({"0004": Payload()}))
    with pytest.raises(InputError, match="not allowed in a data file") as e:
        read_four_d_dress(copy)
    assert "cameras.pkl" in str(e.value) and not marker.exists()


def test_bad_or_partial_takes_are_one_line_errors(take, tmp_path):
    from avatarctl.io.four_d_dress import read_four_d_dress

    copy = tmp_path / "Take1"
    shutil.copytree(take.root, copy)
    (copy / "basic_info.pkl").write_bytes(pickle.dumps({"rotation": np.eye(3)}))
    with pytest.raises(InputError, match="basic_info.pkl has no 'scan_frames'"):
        read_four_d_dress(copy)
    (copy / "basic_info.pkl").unlink()
    assert read_four_d_dress(copy).image_frames["0004"] == {11, 12, 13, 14, 15}  # without it: every image
    (copy / "Capture" / "cameras.pkl").write_bytes(b"\x80\x04 cut")
    with pytest.raises(InputError, match="cannot read cameras.pkl"):
        read_four_d_dress(copy)
    (copy / "Capture" / "cameras.pkl").unlink()
    with pytest.raises(InputError, match="Capture/cameras.pkl missing"):
        read_four_d_dress(copy)
    shutil.rmtree(copy)
    shutil.copytree(take.root, copy, ignore=shutil.ignore_patterns("SMPL*"))
    with pytest.raises(InputError, match="no body fits"):
        read_four_d_dress(copy)


def test_labelled_scans_are_the_ground_truth_geometry(take, tmp_path):
    from avatarctl.io.four_d_dress import ScanGeometry
    from avatarctl.io.gt_geometry import open_gt_geometry

    geo = open_gt_geometry(take.root)
    assert isinstance(geo, ScanGeometry)
    g = geo.frame(12)
    n_body_faces = len(take.faces) - 64  # the skirt cylinder of 16 segments has 64 triangles
    assert len(g.garment_faces) == 64 and len(g.body_faces) == n_body_faces
    np.testing.assert_allclose(g.garment_vertices, take.vertices[1], atol=1e-6)
    with pytest.raises(InputError, match="frame 15 has no labelled scan"):
        geo.frame(15)
    copy = tmp_path / "Take1"
    shutil.copytree(take.root, copy)
    (copy / "Semantic" / "labels" / "label-f00011.pkl").write_bytes(pickle.dumps({"scan_labels": np.zeros(3)}))
    with pytest.raises(InputError, match="labels"):
        open_gt_geometry(copy).frame(11)
    assert open_gt_geometry(tmp_path) is None


def test_ingest_fit_eval_garment_region(random_smplx, take, tmp_path):
    from avatarctl.stages import evaluate, fit, ingest
    from avatarctl.stages.evaluate import EvalConfig
    from avatarctl.stages.fit import FitRequest
    from avatarctl.stages.ingest import IngestConfig

    proj = tmp_path / "proj"
    res = ingest.run(proj, IngestConfig(capture=take.root, project=proj, body_model_path=random_smplx[0],
                                        contact_sheet=False))
    assert res.format == "4d_dress" and res.body_model == "smplx" and res.frames == [11, 12, 13, 14]
    assert res.vertices_inside_masks > 0.97, res.vertices_inside_masks  # extrinsics are world -> camera
    fr = fit.run(proj, FitRequest(preset="micro", iters=2, overrides=("val_every=0",), device="cpu"),
                 handle_sigint=False)
    assert fr.step == 2
    er = evaluate.run(proj, EvalConfig(device="cpu", sheet_rows=0, region="garment"))
    g, b = er.metrics.regions["garment"], er.metrics.regions["body"]
    assert 0 < g["share_of_pixels"] < 1 and g["share_of_pixels"] + b["share_of_pixels"] == pytest.approx(1.0)


def test_benchmark_protocols_name_this_readers_cameras():
    from avatarctl.evaluate.benchmarks import BENCHMARKS
    from avatarctl.frames import parse_frame_spec
    from avatarctl.io.detect import FORMATS

    dress = [p for p in BENCHMARKS.values() if p.dataset == "4d_dress"]
    assert len(dress) == 4 and "4d_dress" in FORMATS
    for p in dress:
        assert set(p.test_views) | set(p.train_views or ()) <= set(FOUR_D_DRESS_CAMERAS)
        parse_frame_spec(p.train_frames), parse_frame_spec(p.test_frames)
        assert p.split == "novel_pose" and p.pixels == "mpmavatar_4d_dress" and any("Take" in t for t in p.traps)
        assert p.sequence.startswith(p.name[-5:] + "/Inner/Take") and p.test_sequence.startswith(p.name[-5:])
