"""`avatarctl render` and `avatarctl eval` on a tiny fitted project (anny body, 4 cameras at 40 px, 3 frames,
fitted with the "micro" preset for a handful of steps: the numbers are meaningless, the files and plumbing are not)."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from avatarctl.errors import InputError, ProjectError
from avatarctl.project import BodyModelRef, Project, SourceRef

pytestmark = pytest.mark.anny

SIZE = 40


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """Project: frames 0, 1 train, frame 2 novel pose; views cam00, cam02 train, cam01, cam03 held out."""
    from fixtures.tiny_project import make_tiny_project

    from avatarctl.fit.config import preset
    from avatarctl.fit.loop import fit
    from avatarctl.io.project_io import Split, save_split

    root = tmp_path_factory.mktemp("re") / "proj"
    project = make_tiny_project(root, size=SIZE, frames=3, cams=4)
    save_split(project.paths.split, Split(train_frames=[0, 1], test_frames=[2], train_views=["cam00", "cam02"],
                                          test_views=["cam01", "cam03"]))
    cfg = replace(preset("micro"), iters=8, checkpoint_every=8, log_every=4)
    fit(project, cfg, device="cpu", handle_sigint=False)
    return root


def _anny_motion_file(path, frames=2):
    from avatarctl.body.anny_model import identity_pose

    pose = identity_pose(frames)
    pose[:, 0, 0, 3] = 5.0  # far away: --recenter must bring it back in front of the cameras
    np.savez(path, body_model=np.array("anny"), pose_parameters=pose, frame_index=np.arange(100, 100 + frames),
             fps=np.array(10.0), phenotype=np.array([0.5], np.float32), phenotype_labels=np.array(["gender"]))
    return path


# ---- render ---------------------------------------------------------------------------------------------------------
def test_render_project_views(fitted):
    from avatarctl.stages.render import RenderConfig
    from avatarctl.stages.render import run as render
    from avatarctl.render.video import probe_video

    res = render(fitted, RenderConfig(name="views", views=("cam01", "cam03"), device="cpu"))
    out = fitted / "render" / "views"
    pngs = sorted((out / "frames").glob("*.png"))
    assert len(pngs) == 6 == len(res.images)  # 3 frames x 2 views
    assert pngs[0].name == "00000_cam01_000000.png"
    img = cv2.imread(str(pngs[0]), cv2.IMREAD_UNCHANGED)
    assert img.shape == (SIZE, SIZE, 3)
    meta = probe_video(out / "video.mp4")
    assert meta["codec"] == "h264" and meta["pix_fmt"] == "yuv420p"
    assert meta["frames"] == 3 and meta["size"] == (2 * SIZE, SIZE)  # two views side by side per frame
    cfg = json.loads((out / "config.json").read_text())
    assert cfg["checkpoint_step"] == 8 and cfg["config"]["views"] == ["cam01", "cam03"]
    assert [im["latent"] for im in cfg["images"]] == ["mean"] * 4 + ["novel"] * 2  # frames 0, 1 train; 2 novel
    rec = Project.open(fitted).last("render")
    assert rec is not None and rec.outputs == ["render/views"] and rec.summary["images"] == 6
    assert not [p for p in (fitted / "render").iterdir() if p.name.startswith(".")]  # no temporaries left


def test_render_orbit_rgba(fitted):
    from avatarctl.stages.render import RenderConfig
    from avatarctl.stages.render import run as render
    from avatarctl.render.video import probe_video

    res = render(fitted, RenderConfig(name="orbit", orbit=5, frames="0", resolution=32, background="transparent",
                                      device="cpu"))
    assert len(res.images) == 5 and {im.view for im in res.images} == {f"orbit{k:03d}" for k in range(5)}
    rgba = cv2.imread(str(fitted / "render" / "orbit" / res.images[0].file), cv2.IMREAD_UNCHANGED)
    assert rgba.shape == (32, 32, 4)
    assert rgba[0, 0, 3] == 0 and rgba[..., 3].max() > 0  # corner transparent, some opacity on the subject
    assert probe_video(res.video)["frames"] == 5
    cams = json.loads((res.out_dir / "config.json").read_text())["cameras"]
    centres = np.array([-np.array(c["R"]).T @ np.array(c["T"]) for c in cams])
    d = np.linalg.norm(centres - centres.mean(0), axis=1)
    assert np.allclose(d, d[0], rtol=1e-6)  # one circle


def test_render_with_anny_motion_file(fitted, tmp_path):
    from avatarctl.stages.render import RenderConfig
    from avatarctl.stages.render import run as render

    motion = _anny_motion_file(tmp_path / "motion.npz")
    res = render(fitted, RenderConfig(name="poses", poses=str(motion), views=("cam01",), device="cpu"))
    assert [im.frame for im in res.images] == [100, 101] and {im.latent for im in res.images} == {"novel"}
    assert res.fps == pytest.approx(10.0)
    # recentred onto the training subject: the body is in view (some rays reach the nodes)
    assert all(im.rays > 0 for im in res.images)
    far = render(fitted, RenderConfig(name="far", poses=str(motion), views=("cam01",), recenter=False, device="cpu"))
    assert all(im.rays == 0 for im in far.images)  # 5 m away and behind the ring of cameras: nothing hit


def test_render_retargets_an_amass_walk_onto_the_anny_avatar(fitted, tmp_path):
    from fixtures.smpl import smpl_walk, write_amass_npz

    from avatarctl.stages.render import RenderConfig
    from avatarctl.stages.render import run as render

    poses, trans = smpl_walk(4, fps=10.0)
    amass = write_amass_npz(tmp_path / "walk_poses.npz", poses, trans, fps=10.0)
    res = render(fitted, RenderConfig(name="amass", poses=str(amass), views=("cam01",), device="cpu"))
    assert res.retarget is not None and "retargeted smplh" in res.retarget and "-> anny" in res.retarget
    assert [im.frame for im in res.images] == [0, 1, 2, 3] and all(im.rays > 0 for im in res.images)
    record = json.loads((res.out_dir / "config.json").read_text())
    assert record["retarget"] == res.retarget


def test_render_errors_are_one_line_and_write_nothing(fitted, tmp_path):
    from avatarctl.stages.render import RenderConfig
    from avatarctl.stages.render import run as render

    amass = tmp_path / "amass.npz"
    np.savez(amass, poses=np.zeros((2, 156)), trans=np.zeros((2, 3)), betas=np.zeros(16), mocap_frame_rte=120.0)
    with pytest.raises(InputError, match="frame-rate key 'mocap_frame_rte'"):
        render(fitted, RenderConfig(name="bad1", poses=str(amass), device="cpu"))
    with pytest.raises(InputError, match="latent mean needs training frames"):
        render(fitted, RenderConfig(name="bad2", frames="test", latent="mean", device="cpu"))
    with pytest.raises(InputError, match="unknown camera"):
        render(fitted, RenderConfig(name="bad3", views=("cam09",), device="cpu"))
    assert not any((fitted / "render" / n).exists() for n in ("bad1", "bad2", "bad3"))


def test_render_failure_midway_leaves_no_output(fitted, monkeypatch):
    import avatarctl.render.engine as engine
    from avatarctl.stages.render import RenderConfig
    from avatarctl.stages.render import run as render

    calls = {"n": 0}
    real = engine.render_view

    def flaky(*a, **k):
        calls["n"] += 1
        if calls["n"] == 2:
            raise RuntimeError("simulated crash")
        return real(*a, **k)

    monkeypatch.setattr(engine, "render_view", flaky)
    before = len(Project.open(fitted).manifest.stages)
    with pytest.raises(RuntimeError, match="simulated"):
        render(fitted, RenderConfig(name="crash", frames="0:2", device="cpu"))
    assert not (fitted / "render" / "crash").exists()
    assert not [p for p in (fitted / "render").iterdir() if p.name.startswith(".crash")]
    assert len(Project.open(fitted).manifest.stages) == before


# ---- eval -----------------------------------------------------------------------------------------------------------
def test_eval_novel_view_writes_metrics_csv_sheet(fitted):
    from avatarctl.evaluate.report import read_per_frame_csv
    from avatarctl.stages.evaluate import EvalConfig
    from avatarctl.stages.evaluate import run as evaluate

    res = evaluate(fitted, EvalConfig(split="novel_view", protocol="bbox", device="cpu"))
    out = fitted / "eval" / "novel_view_bbox"
    m = json.loads((out / "metrics.json").read_text())
    for key in ("split", "protocol", "psnr", "ssim", "frames", "views", "checkpoint_step", "metric_settings",
                "background", "latent", "lpips", "lpips_reason", "ground_truth"):
        assert key in m, key
    assert m["split"] == "novel_view" and m["protocol"] == "bbox" and m["checkpoint_step"] == 8
    assert m["frames"] == [0, 1] and m["views"] == ["cam01", "cam03"] and m["latent"] == "mean"
    assert math.isfinite(m["psnr"]) and 0 < m["psnr"] < 60 and -1 <= m["ssim"] <= 1
    assert m["lpips"] is None or math.isfinite(m["lpips"])
    assert m["lpips"] is not None or m["lpips_reason"]
    rows = read_per_frame_csv(out / "per_frame.csv")
    assert [(r["frame"], r["view"]) for r in rows] == [(0, "cam01"), (0, "cam03"), (1, "cam01"), (1, "cam03")]
    assert np.mean([r["psnr"] for r in rows]) == pytest.approx(m["psnr"], abs=1e-3)
    assert cv2.imread(str(out / "sheet.png")) is not None
    assert res.psnr == pytest.approx(m["psnr"])
    assert res.metrics.to_json() == m  # the typed result is the file, key for key
    rec = Project.open(fitted).last("eval")
    assert rec.summary["split"] == "novel_view" and rec.outputs == ["eval/novel_view_bbox"]


def test_eval_scores_against_masked_ground_truth(fitted, monkeypatch):
    """With a renderer that returns only the background, every per-image score must equal a hand computation
    against gt = image * mask + background * (1 - mask) inside the projected body box."""
    import avatarctl.render.engine as engine
    from avatarctl.body.registry import load_body_model
    from avatarctl.evaluate import metrics
    from avatarctl.evaluate.protocols import bbox_region
    from avatarctl.stages.evaluate import EvalConfig
    from avatarctl.stages.evaluate import run as evaluate
    from avatarctl.io.project_io import load_project_capture

    def background_only(model, state, slot, camera, background, max_rays_per_chunk=8192, pixel_mask=None,
                        progress=None):
        rgb = np.empty((camera.height, camera.width, 3), np.float32)
        rgb[:] = background
        return engine.ViewRender(rgb=rgb, alpha=np.zeros(rgb.shape[:2], np.float32), seconds=0.0)

    monkeypatch.setattr(engine, "render_view", background_only)
    res = evaluate(fitted, EvalConfig(split="novel_pose", protocol="bbox", name="bg_only", device="cpu"))
    cap = load_project_capture(Project.open(fitted))
    body = load_body_model("anny")
    verts = body.pose(cap.motion.for_frames([2])).vertices[0].numpy()
    bg = np.asarray(res.metrics.background, np.float32)
    assert [(s.frame, s.view) for s in res.scores] == [(2, "cam01"), (2, "cam03")]
    for s in res.scores:
        cam = cap.cameras[s.view]
        img = cap.image(s.view, 2).astype(np.float32) / 255
        m = cap.mask(s.view, 2)[..., None]
        gt = img * m + bg * (1 - m)
        region = bbox_region(cam, verts)
        pred = np.broadcast_to(bg, gt.shape)
        assert s.psnr == pytest.approx(metrics.psnr(pred, gt, region.mask), abs=1e-4)
        assert s.ssim == pytest.approx(metrics.ssim(region.crop_image(pred), region.crop_image(gt)), abs=1e-5)
    assert res.metrics.latent == "novel"


def test_eval_full_protocol_and_every(fitted):
    from avatarctl.stages.evaluate import EvalConfig
    from avatarctl.stages.evaluate import run as evaluate

    from avatarctl.evaluate import metrics
    from avatarctl.io.project_io import load_project_capture

    res = evaluate(fitted, EvalConfig(split="train", protocol="full", every=2, views=("cam00",), sheet_rows=0,
                                      device="cpu", save_images=True))
    assert res.metrics.frames == [0] and res.metrics.views == ["cam00"] and res.metrics.every == 2
    assert res.scores[0].pixels == SIZE * SIZE
    assert not (res.out_dir / "sheet.png").exists()
    # --save-images: the image that was scored, as an 8-bit PNG
    assert [p.name for p in (res.out_dir / "renders").iterdir()] == ["000000_cam00.png"]
    saved = cv2.imread(str(res.out_dir / "renders" / "000000_cam00.png"))[..., ::-1].astype(np.float32) / 255
    cap = load_project_capture(Project.open(fitted))
    m = cap.mask("cam00", 0)[..., None]
    bg = np.asarray(res.metrics.background, np.float32)
    gt = cap.image("cam00", 0).astype(np.float32) / 255 * m + bg * (1 - m)
    assert metrics.psnr(saved, gt) == pytest.approx(res.scores[0].psnr, abs=0.05)


def test_eval_errors(fitted):
    from avatarctl.stages.evaluate import EvalConfig
    from avatarctl.stages.evaluate import run as evaluate

    with pytest.raises(InputError, match="unknown split"):
        EvalConfig(split="novel")
    with pytest.raises(InputError, match="unknown protocol"):
        EvalConfig(protocol="crop")
    with pytest.raises(InputError, match="latent mean needs training frames"):
        evaluate(fitted, EvalConfig(split="novel_pose", latent="mean", name="x", device="cpu"))
    assert not (fitted / "eval" / "x").exists()


def test_compare_projects(fitted, tmp_path):
    import shutil

    from avatarctl.evaluate.compare import compare, latest_metrics
    from avatarctl.stages.evaluate import EvalConfig
    from avatarctl.stages.evaluate import run as evaluate

    evaluate(fitted, EvalConfig(split="novel_view", protocol="bbox", device="cpu"))
    other = tmp_path / "other"
    shutil.copytree(fitted, other)
    m_path = other / "eval" / "novel_view_bbox" / "metrics.json"
    m = json.loads(m_path.read_text())
    m["psnr"], m["frames"] = 99.0, [0]
    m["model"]["ablations"] = ["no-delta-n", "no-embedding"]
    m_path.write_text(json.dumps(m))
    rows = compare([fitted, other], split="novel_view", protocol="bbox")
    assert [r.label for r in rows] == ["full model", "no-delta-n, no-embedding"]
    assert rows[1].psnr == 99.0 and rows[0].same_images and not rows[1].same_images
    with pytest.raises(ProjectError, match="no eval results for --split novel_view --protocol full"):
        latest_metrics(Project.open(fitted), "novel_view", "full")
    res = CliRunner().invoke(_app(), ["eval", str(fitted), "--compare", str(other)])
    assert res.exit_code == 0, res.output
    assert "99.000" in res.output and "full model" in res.output


# ---- CLI ------------------------------------------------------------------------------------------------------------
def _app():
    from avatarctl.cli.app import app

    return app


def test_cli_render_and_eval(fitted):
    runner = CliRunner()
    res = runner.invoke(_app(), ["render", str(fitted), "--orbit", "2", "--frames", "1", "--resolution", "24",
                                 "--name", "cli", "--device", "cpu"])
    assert res.exit_code == 0, res.output
    assert "video.mp4" in res.output and (fitted / "render" / "cli" / "video.mp4").is_file()
    res = runner.invoke(_app(), ["eval", str(fitted), "--split", "novel_pose", "--name", "cli", "--device", "cpu"])
    assert res.exit_code == 0, res.output
    assert "PSNR" in res.output and (fitted / "eval" / "cli" / "metrics.json").is_file()
    res = runner.invoke(_app(), ["render", str(fitted), "--views", "cam01", "--orbit", "3"])
    assert res.exit_code == 2 and "exclusive" in res.output
    res = runner.invoke(_app(), ["eval", str(fitted), str(fitted)])
    assert res.exit_code == 2 and "--compare" in res.output


def test_render_needs_a_fit(tmp_path):
    from avatarctl.stages.render import RenderConfig
    from avatarctl.stages.render import run as render

    Project.create(tmp_path / "p", body_model=BodyModelRef("anny"), source=SourceRef("x", "synthetic", "", 0))
    with pytest.raises(ProjectError, match="no fit output"):
        render(tmp_path / "p", RenderConfig())


def test_relative_project_path_records_outputs_under_the_root(fitted, monkeypatch):
    from avatarctl.stages.render import RenderConfig
    from avatarctl.stages.render import run as render

    monkeypatch.chdir(fitted.parent)
    render(fitted.name, RenderConfig(name="rel", frames="0", device="cpu"))
    rec = Project.open(fitted.name).require("render")  # raises if the recorded outputs do not resolve
    assert rec.outputs == ["render/rel"]
