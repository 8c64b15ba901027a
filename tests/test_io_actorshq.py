"""The ActorsHQ reader (`avatarctl.io.actorshq`): calibration.csv's conventions checked on hand-written rows (not
through our own writer), the release's file naming on a toy capture in its layout (`fixtures.actorshq`), detection,
ingest, and one line for every bad or partial folder."""

from __future__ import annotations

import math
import shutil

import numpy as np
import pytest
from fixtures.actorshq import CAMS, make_toy_actorshq
from fixtures.cli_errors import assert_one_line_error
from typer.testing import CliRunner

from avatarctl.cli.app import app
from avatarctl.errors import InputError

HEADER = "name,w,h,rx,ry,rz,tx,ty,tz,fx,fy,px,py\n"


def test_calibration_csv_is_camera_to_world_with_normalised_intrinsics(tmp_path):
    from avatarctl.io.actorshq import read_actorshq_cameras

    # CamA at (0, 0, -3) looking along +z (no rotation); CamB rotated +90 deg about y, so its optical axis is world
    # +x and its image x axis world -z, at (-3, 0, 0). Intrinsics normalised: fx * w, fy * h, px * w, py * h.
    (tmp_path / "calibration.csv").write_text(
        HEADER + "CamA,200,100,0,0,0,0,0,-3,1.5,2.5,0.5,0.4\n"
        + f"CamB,200,100,0,{math.pi / 2!r},0,-3,0,0,1.5,2.5,0.5,0.4\n")
    a, b = read_actorshq_cameras(tmp_path / "calibration.csv")
    assert (a.name, a.width, a.height) == ("CamA", 200, 100)
    np.testing.assert_allclose(a.K, [[300, 0, 100], [0, 250, 40], [0, 0, 1]])
    assert np.allclose(a.dist, 0)
    # the origin lies on both optical axes, 3 m away: it projects to the principal point
    for cam in (a, b):
        np.testing.assert_allclose(cam.project(np.zeros((1, 3)))[0], [100, 40], atol=1e-9)
    # 0.3 m along each camera's image x axis at 3 m depth: 0.1 * fx_px to the right of the principal point
    np.testing.assert_allclose(a.project(np.array([[0.3, 0.0, 0.0]]))[0], [130, 40], atol=1e-9)
    np.testing.assert_allclose(b.project(np.array([[0.0, 0.0, -0.3]]))[0], [130, 40], atol=1e-9)
    # and 0.3 m down (image y = world +y for both): 0.1 * fy_px below
    np.testing.assert_allclose(b.project(np.array([[0.0, 0.3, 0.0]]))[0], [100, 65], atol=1e-9)


def test_reader_on_a_capture_in_the_release_layout(tmp_path):
    from avatarctl.io.actorshq import read_actorshq
    from avatarctl.io.detect import detect_format

    scale_dir = make_toy_actorshq(tmp_path, frames=(460, 461, 660))
    for root in (scale_dir, scale_dir.parent):  # the scale folder, or the sequence folder holding one
        assert detect_format(root)[0] == "actorshq"
        src = read_actorshq(root)
        assert src.format == "actorshq" and src.camera_names == list(CAMS)
        assert src.image_frames == {c: {460, 461, 660} for c in CAMS} == src.mask_frames
        assert src.sequence == "Actor01/Sequence1" and src.release_scale == 0.25
        assert src.fits is not None and src.fits_where.endswith("Sequence1/motion.npz")
        assert src.images.where("Cam007", 660).endswith("rgbs/Cam007/Cam007_rgb000660.jpg")
        img, mask = src.images.read("Cam127", 460), src.masks.read("Cam127", 460)
        assert img.shape == (32, 32, 3) and mask.dtype == bool and 0 < mask.mean() < 0.9
    # the written calibration reads back as the cameras it was made from
    from fixtures.tiny_project import ring_cameras

    for got, want in zip(read_actorshq(scale_dir).cameras, ring_cameras(len(CAMS), 32, radius=1.6)):
        np.testing.assert_allclose(got.K, want.K, atol=1e-9)
        np.testing.assert_allclose(got.R, want.R, atol=1e-9)
        np.testing.assert_allclose(got.T, want.T, atol=1e-9)


def test_ingest_of_an_actorshq_capture(tmp_path):
    from avatarctl.io.project_io import load_project_capture
    from avatarctl.project import Project
    from avatarctl.stages import ingest
    from avatarctl.stages.ingest import IngestConfig

    scale_dir = make_toy_actorshq(tmp_path / "cap", frames=(0, 1, 2))
    proj = tmp_path / "proj"
    res = ingest.run(proj, IngestConfig(capture=scale_dir.parent, project=proj, contact_sheet=False))
    assert res.format == "actorshq" and res.cameras == list(CAMS) and res.frames == [0, 1, 2]
    assert res.body_model == "toy" and res.vertices_inside_masks > 0.9 and res.resolution == (32, 32)
    pc = load_project_capture(Project.open(proj))
    assert pc.split.test_views == ["Cam127"]  # no benchmark: the default split (every 4th view)
    assert not Project.open(proj).paths.benchmark.exists()


def _without_masks_of(scale_dir, cam, frame):
    from avatarctl.io.actorshq import mask_path

    mask_path(scale_dir, cam, frame).unlink()


def _extra_camera(scale_dir):
    shutil.copytree(scale_dir / "rgbs" / "Cam050", scale_dir / "rgbs" / "Cam151")


def _no_images_for(scale_dir):
    shutil.rmtree(scale_dir / "rgbs" / "Cam050")


def _csv_without(scale_dir, column):
    p = scale_dir / "calibration.csv"
    rows = [r.split(",") for r in p.read_text().splitlines()]
    i = rows[0].index(column)
    p.write_text("\n".join(",".join(r[:i] + r[i + 1:]) for r in rows) + "\n")


def _csv_garbled(scale_dir):
    p = scale_dir / "calibration.csv"
    p.write_text(p.read_text().replace("Cam007,32,32,", "Cam007,32,x32,"))


@pytest.mark.parametrize("breakage, at_sequence, needles", [
    (lambda d: _without_masks_of(d, "Cam007", 1), False, ("camera Cam007", "masks", "frames 1")),
    (_extra_camera, False, ("extra cameras", "Cam151")),
    (_no_images_for, False, ("camera Cam050 has no images",)),
    (lambda d: _csv_without(d, "fy"), False, ("calibration.csv lacks the column(s) fy",)),
    (_csv_garbled, False, ("calibration.csv line 3 (camera Cam007) has a non-numeric value",)),
    (lambda d: shutil.copytree(d, d.parent / "1x"), True, ("several scales (1x, 4x)",)),
    (lambda d: shutil.rmtree(d / "rgbs"), False, ("no rgbs/ folder",)),
])
def test_a_bad_or_partial_folder_is_one_line(tmp_path, breakage, at_sequence, needles):
    scale_dir = make_toy_actorshq(tmp_path / "cap", frames=(0, 1))
    breakage(scale_dir)
    proj = tmp_path / "proj"
    res = CliRunner().invoke(app, ["ingest", str(scale_dir.parent if at_sequence else scale_dir), str(proj),
                                   "--format", "actorshq", "--no-contact-sheet"])
    assert_one_line_error(res, proj, *needles)


def test_a_renamed_scale_folder_is_taken_as_full_resolution(tmp_path):
    from avatarctl.io.actorshq import read_actorshq

    scale_dir = make_toy_actorshq(tmp_path, frames=(0,))
    src = read_actorshq(scale_dir.rename(tmp_path / "renamed"))
    assert src.release_scale == 1.0 and src.sequence == "" and any("'renamed' is not named" in n for n in src.notes)


def test_the_release_ships_no_fits(tmp_path):
    from avatarctl.io.actorshq import read_actorshq

    src = read_actorshq(make_toy_actorshq(tmp_path, frames=(0,), fits=False))
    assert src.fits is None and any("--fits keypoints" in n for n in src.notes)


def test_a_folder_without_calibration_is_not_actorshq(tmp_path):
    from avatarctl.io.actorshq import is_actorshq, resolve_scale_folder

    (tmp_path / "Sequence1" / "4x" / "rgbs").mkdir(parents=True)
    assert not is_actorshq(tmp_path / "Sequence1") and not is_actorshq(tmp_path / "Sequence1" / "4x")
    with pytest.raises(InputError, match="no calibration.csv"):
        resolve_scale_folder(tmp_path / "Sequence1")
