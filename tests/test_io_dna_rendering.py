"""DNA-Rendering (`avatarctl.io.dna_rendering`) on a synthetic SMC pair in the release's exact layout
(`fixtures.dataset_layouts`): detection, the quirks (padded calibration keys and unpadded image keys, camera ->
world RT, BGR JPEG bytes, 3-channel JPEG masks, SMPLx fullpose, the annotations in the release's sibling folder),
reading per (camera, frame), one-line errors for bad or partial files, and ingest -> micro fit -> eval."""

from __future__ import annotations

import numpy as np
import pytest
from fixtures.dataset_layouts import DNA_CAMERA_IDS, make_dna_rendering_capture

from avatarctl.errors import InputError


@pytest.fixture(scope="module")
def capture(random_smplx, tmp_path_factory):
    return make_dna_rendering_capture(tmp_path_factory.mktemp("dna") / "0007_04", random_smplx[1])


def test_reader_reads_the_release_layout(capture):
    import cv2

    from avatarctl.io.detect import detect_format
    from avatarctl.io.dna_rendering import read_dna_rendering

    fmt, reason = detect_format(capture.root)
    assert fmt == "dna_rendering" and "0007_04.smc" in reason
    calls = []
    real = cv2.imdecode
    cv2.imdecode = lambda *a, **k: calls.append(1) or real(*a, **k)
    try:
        src = read_dna_rendering(capture.root)
        assert calls == [], "reading the capture decodes no image (sizes come from the JPEG headers)"
        rgb = src.images.read("48", 1)
        assert len(calls) == 1, "one (camera, frame) decodes one image"
    finally:
        cv2.imdecode = real
    assert src.camera_names == [f"{i:02d}" for i in DNA_CAMERA_IDS]
    by = {c.name: c for c in src.cameras}
    for want in capture.cameras:  # RT is camera -> world; the reader gives OpenCV world -> camera
        got = by[want.name]
        np.testing.assert_allclose(got.R, want.R, atol=1e-9)
        np.testing.assert_allclose(got.T, want.T, atol=1e-9)
        np.testing.assert_allclose(got.dist, want.dist, atol=1e-12)
        assert (got.width, got.height) == (want.width, want.height)
    assert (by["48"].width, by["48"].height) != (by["00"].width, by["00"].height)  # the 12 MP ring's own size
    assert src.image_frames == {n: {0, 1, 2} for n in src.camera_names}
    assert src.mask_frames == src.image_frames

    # colour: the file holds BGR JPEG bytes; the reader returns RGB
    from fixtures.captures import plate, render

    cam = capture.cameras[2]
    want_rgb, sil = render(cam, capture.vertices[1], capture.faces, plate(cam, 2))
    assert rgb.shape == (cam.height, cam.width, 3)
    err = np.abs(rgb.astype(float) - want_rgb).mean()
    assert err < 3 and err < 0.3 * np.abs(rgb[..., ::-1].astype(float) - want_rgb).mean(), err
    # masks: 3-channel JPEG, foreground where the decoded grey is above half
    m = src.masks.read("48", 1)
    assert m.dtype == bool and (m & sil).sum() / (m | sil).sum() > 0.98
    # fits: fullpose [F, 55, 3] split into SMPL-X parts, the per-frame betas averaged
    fits = src.fits
    assert fits.body_model == "smplx" and list(fits.frame_index) == [0, 1, 2]
    for key in ("global_orient", "body_pose", "jaw_pose", "left_hand_pose", "right_hand_pose", "transl",
                "expression"):
        np.testing.assert_allclose(getattr(fits, key), getattr(capture.motion, key), atol=1e-9, err_msg=key)
    np.testing.assert_allclose(fits.betas, capture.motion.betas, atol=1e-9)
    assert any("hand mean" in n for n in src.notes)


def test_annotations_found_in_the_release_folder(random_smplx, tmp_path):
    from avatarctl.io.dna_rendering import read_dna_rendering

    cap = make_dna_rendering_capture(tmp_path, random_smplx[1], frames=[0], annots_beside=False)
    assert cap.root.name == "dna_rendering_part1_main" and not list(cap.root.glob("*_annots.smc"))
    src = read_dna_rendering(cap.root)
    assert src.fits is not None and src.masks is not None and len(src.cameras) == 4


def test_bad_or_partial_folders_are_one_line_errors(capture, tmp_path):
    import h5py

    from avatarctl.io.dna_rendering import read_dna_rendering

    with pytest.raises(InputError, match=r"no DNA-Rendering main file"):
        read_dna_rendering(tmp_path)
    (tmp_path / "0007_04.smc").symlink_to(capture.root / "0007_04.smc")
    with pytest.raises(InputError, match=r"annotations file 0007_04_annots.smc missing") as e:
        read_dna_rendering(tmp_path)
    assert "\n" not in str(e.value)
    (tmp_path / "0008_01.smc").write_bytes(b"not hdf5")
    with pytest.raises(InputError, match="2 DNA-Rendering sequences"):
        read_dna_rendering(tmp_path)
    (tmp_path / "0008_01.smc").unlink()
    (tmp_path / "0007_04_annots.smc").write_bytes(b"\x89HDF cut off")
    with pytest.raises(InputError, match="cannot open 0007_04_annots.smc as HDF5"):
        read_dna_rendering(tmp_path)
    (tmp_path / "0007_04_annots.smc").unlink()
    with h5py.File(capture.root / "0007_04_annots.smc") as src, h5py.File(tmp_path / "0007_04_annots.smc", "w") as d:
        src.copy("Camera_Parameter", d)
        src.copy("Mask", d)
        d.create_group("SMPLx")["transl"] = src["SMPLx/transl"][()]
    with pytest.raises(InputError, match="SMPLx lacks fullpose, betas"):
        read_dna_rendering(tmp_path)
    with h5py.File(capture.root / "0007_04_annots.smc") as src, h5py.File(tmp_path / "0007_04_annots.smc", "a") as d:
        del d["SMPLx"], d["Mask/48"], d["Camera_Parameter/50"]
        src.copy("SMPLx", d)
    src = read_dna_rendering(tmp_path)
    assert src.fits is not None and src.uncalibrated == ["50"] and src.mask_frames["48"] == set()
    from avatarctl.ingest.config import IngestConfig
    from avatarctl.ingest.pipeline import plan_ingest

    with pytest.raises(InputError, match="camera 48 has no masks"):  # ingest names the camera without masks
        plan_ingest(IngestConfig(capture=tmp_path, project=tmp_path.parent / "p_missing", views=("00", "48")))
    with h5py.File(tmp_path / "0007_04_annots.smc", "a") as d:
        del d["SMPLx"]
    src = read_dna_rendering(tmp_path)
    assert src.fits is None and any("no SMPLx group" in n for n in src.notes)


def test_ingest_fit_eval(random_smplx, capture, tmp_path):
    from avatarctl.stages import evaluate, fit, ingest
    from avatarctl.stages.evaluate import EvalConfig
    from avatarctl.stages.fit import FitRequest
    from avatarctl.stages.ingest import IngestConfig

    proj = tmp_path / "proj"
    res = ingest.run(proj, IngestConfig(capture=capture.root, project=proj, body_model_path=random_smplx[0],
                                        contact_sheet=False))
    assert res.format == "dna_rendering" and res.body_model == "smplx" and res.masks_source == "files"
    assert res.cameras == ["00", "02", "48", "50"] and res.frames == [0, 1, 2]
    assert res.vertices_inside_masks > 0.97, res.vertices_inside_masks  # RT inverted, fullpose split right
    # the hands stored as offsets from the model's hand mean are ingested as full axis-angle poses (+ the mean)
    from avatarctl.io.project_io import load_project_capture
    from avatarctl.project import Project

    got = load_project_capture(Project.open(proj)).motion
    mean = random_smplx[1].data.hands_mean.reshape(2, 45)
    stored = capture.motion.for_frames([0, 1, 2])
    assert np.allclose(got.left_hand_pose, stored.left_hand_pose + mean[0], atol=1e-5)
    assert np.allclose(got.right_hand_pose, stored.right_hand_pose + mean[1], atol=1e-5)
    fr = fit.run(proj, FitRequest(preset="micro", iters=2, overrides=("val_every=0",), device="cpu"),
                 handle_sigint=False)
    assert fr.step == 2
    er = evaluate.run(proj, EvalConfig(device="cpu", sheet_rows=0, region="edge"))
    assert er.metrics.images > 0 and 0 < er.psnr < 100
    with pytest.raises(InputError, match="ground-truth garment geometry"):  # DNA-Rendering ships no meshes
        evaluate.run(proj, EvalConfig(device="cpu", sheet_rows=0, region="garment", name="garment"))


def test_benchmark_protocols_name_this_readers_cameras():
    from avatarctl.evaluate.benchmarks import BENCHMARKS
    from avatarctl.frames import parse_frame_spec
    from avatarctl.io.detect import FORMATS
    from avatarctl.io.dna_rendering import camera_name

    dna = [p for p in BENCHMARKS.values() if p.dataset == "dna_rendering"]
    assert dna and "dna_rendering" in FORMATS
    for p in dna:
        views = set(p.test_views) | set(p.train_views or ())
        assert all(v == camera_name(int(v)) and 0 <= int(v) < 60 for v in views), views
        assert not set(p.test_views) & set(p.train_views or ()) and p.split == "novel_view"
        parse_frame_spec(p.train_frames), parse_frame_spec(p.test_frames)
        assert p.pixels in ("full", "bbox") and 0 < p.scale <= 1 and p.comparable_with
