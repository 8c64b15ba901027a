"""`avatarctl export` on a fitted toy-sphere project: files, record, reload check, other outputs untouched, errors."""

from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest

from avatarctl.errors import InputError
from avatarctl.project import Project

FAST = dict(voxel=0.03, threshold=0.3, device="cpu")  # a 10-step toy fit is faint: a low surface level



def _digest(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_export_writes_meshes_skinned_avatar_and_record(toy_fitted_project):
    from avatarctl.stages import export
    from avatarctl.stages.export import ExportConfig

    ckpt = Project.open(toy_fitted_project).paths.latest_checkpoint
    before = _digest(ckpt)
    seen = []
    res = export.run(toy_fitted_project, ExportConfig(frames="0,3", formats=("glb", "ply"), score=True, **FAST),
                     progress=seen.append)
    out = res.out_dir
    assert [m.frame for m in res.meshes] == [0, 3] and [m.latent for m in res.meshes] == ["mean", "novel"]
    for m in res.meshes:
        assert m.vertices > 100 and m.faces > 100
        assert all((out / f).stat().st_size == b for f, b in m.files.items())
    assert (out / "avatar.glb").is_file() and (out / "preview.png").is_file()
    rec = json.loads((out / "export.json").read_text())
    assert rec["config"]["formats"] == ["glb", "ply"] and rec["avatar"]["joints"] == 2
    assert rec["avatar"]["animation_frames"] == 4 and rec["avatar"]["animation_source"] == "project"
    reload = rec["avatar"]["reload"]
    if reload["checked"]:  # pygltflib installed
        assert reload["vs_lbs_same_weights_max_m"] < 1e-5 and reload["default_pose_max_m"] < 1e-5
    assert {s.split for s in res.scores} == {"novel_view", "novel_pose"} and len(res.scores) == 4
    assert all(np.isfinite([s.psnr_mesh, s.psnr_volume]).all() for s in res.scores)
    assert Project.open(toy_fitted_project).manifest.stages[-1].stage == "export"
    assert _digest(ckpt) == before, "the fit is untouched"
    assert seen[-1].stage == "export" and seen[-1].done == seen[-1].total == 3


def test_export_with_a_motion_file_animates_it(toy_fitted_project, tmp_path):
    from fixtures.toy_capture import toy_motion

    from avatarctl.stages import export
    from avatarctl.stages.export import ExportConfig

    toy_motion(7).save(tmp_path / "walk.npz")
    res = export.run(toy_fitted_project, ExportConfig(name="walk", poses=str(tmp_path / "walk.npz"), frames="6",
                                               formats=("obj",), **FAST))
    assert res.avatar.animation_frames == 7 and res.avatar.animation_source.endswith("walk.npz")
    assert [m.latent for m in res.meshes] == ["novel"] and (res.out_dir / "meshes" / "000006.obj").is_file()


@pytest.mark.parametrize("kw, match", [
    (dict(formats=("fbx",)), "unknown mesh format"),
    (dict(voxel=0.5), "--voxel"),
    (dict(threshold=0.0), "--threshold"),
    (dict(influences=5), "--influences"),
    (dict(posed=False, skinned=False), "nothing to export"),
    (dict(poses="x.npz", score=True), "--score needs"),
    (dict(name="a/b"), "invalid export name"),
])
def test_config_errors(kw, match):
    from avatarctl.errors import AvatarError
    from avatarctl.stages.export import ExportConfig

    with pytest.raises(AvatarError, match=match):
        ExportConfig(**kw)


def test_no_surface_is_a_one_line_error_and_writes_nothing(toy_fitted_project):
    from avatarctl.stages import export
    from avatarctl.stages.export import ExportConfig

    with pytest.raises(InputError, match="no surface to mesh for frame 0.*lower --threshold"):
        export.run(toy_fitted_project, ExportConfig(name="high", voxel=0.03, threshold=1e6, device="cpu"))
    assert not (toy_fitted_project / "export" / "high").exists()


def test_cli_errors_exit_non_zero_without_traceback(toy_fitted_project, tmp_path):
    from typer.testing import CliRunner

    from avatarctl.cli.app import app

    r = CliRunner().invoke(app, ["export", str(toy_fitted_project), "--poses", str(tmp_path / "missing.npz")])
    assert r.exit_code == 2 and "motion file not found" in r.output and "Traceback" not in r.output
    r = CliRunner().invoke(app, ["export", str(toy_fitted_project), "--threshold", "high"])
    assert r.exit_code == 2 and "--threshold 'high' is not a number" in r.output and "Traceback" not in r.output
    r = CliRunner().invoke(app, ["export", str(tmp_path / "nowhere")])
    assert r.exit_code != 0 and "Traceback" not in r.output


def _ground_export(project):
    from avatarctl.stages import export
    from avatarctl.stages.export import ExportConfig

    out = project / "export" / "ground"
    if not out.exists():
        export.run(project, ExportConfig(name="ground", frames="0,3", formats=("glb", "ply"), **FAST))
    return out


def test_glb_files_stand_on_the_ground_under_the_body(toy_fitted_project):
    """GLB origin: height 0 = the lowest point of the body template over the motion, the middle of the first frame's
    footprint at x = z = 0; +Y up; posed GLBs = the PLY's world vertices in that frame; avatar.glb's default pose is
    its first animation frame."""
    pytest.importorskip("pygltflib")
    trimesh = pytest.importorskip("trimesh")
    from avatarctl.export.gltf_read import pose_glb, read_skinned_glb
    from avatarctl.export.skinning import to_frame
    from avatarctl.stages.common import load_fitted, open_fitted

    out = _ground_export(toy_fitted_project)
    A = np.array(json.loads((out / "export.json").read_text())["glb_frame"])
    avatar = load_fitted(open_fitted(toy_fitted_project, None), "cpu", None)
    body = to_frame(avatar.body.pose(avatar.capture.motion).vertices.double().numpy(), A)  # [frames, V, 3]
    assert body[..., 1].min() == pytest.approx(0.0, abs=1e-6), "the lowest foot point on y = 0"
    mid = 0.5 * (body[0].min(0) + body[0].max(0))
    assert np.abs(mid[[0, 2]]).max() < 1e-6, "the origin under the body in the first frame"
    up = A[:3, :3] @ avatar.capture.cameras[next(iter(avatar.capture.cameras))].R[1] * -1.0
    assert up[1] > 0.9, "+Y up"
    for frame in (0, 3):
        ply = trimesh.load(str(out / "meshes" / f"{frame:06d}.ply"), process=False)
        glb = trimesh.load(str(out / "meshes" / f"{frame:06d}.glb"), force="mesh", process=False)
        assert np.abs(to_frame(ply.vertices, A) - glb.vertices).max() < 1e-5
    data = read_skinned_glb(out / "avatar.glb")
    assert np.abs(pose_glb(data) - pose_glb(data, 0, 0)).max() < 1e-6, "shown without animation: the first frame"


@pytest.mark.node
def test_every_exported_glb_passes_the_khronos_validator(toy_fitted_project):
    from fixtures.node import npm_modules, validate_gltf

    if npm_modules() is None:
        pytest.skip("no node / npm, or npm could not install gltf-validator")
    out = _ground_export(toy_fitted_project)
    files = sorted(out.rglob("*.glb"))
    assert len(files) == 3
    for path in files:
        report = validate_gltf(path)
        assert report["errors"] == 0 and report["warnings"] == 0, (path.name, report)


def _in_file_frame(camera, A: np.ndarray, scale: float = 1.0):
    """A world camera as the same camera in the GLB file's frame (x_file = A x_world), its image `scale`d."""
    from avatarctl.geometry.cameras import Camera

    C, t = A[:3, :3], A[:3, 3]
    K = np.diag([scale, scale, 1.0]) @ camera.K
    K[:2, 2] = (camera.K[:2, 2] + 0.5) * scale - 0.5  # pixel centres at integer coordinates
    return Camera(camera.name, K=K, R=camera.R @ C.T, T=camera.T - camera.R @ C.T @ t,
                  width=round(camera.width * scale), height=round(camera.height * scale))


@pytest.mark.browser
@pytest.mark.node
def test_avatar_glb_in_three_js_matches_the_file_posed_by_us(toy_fitted_project):
    """The stage's avatar.glb in three.js (GLTFLoader + AnimationMixer, headless Chromium): one SkinnedMesh with the
    body's bones and the unlit material; at two animation times three.js's own skinning has the lowest point we
    compute and the images differ; each has the silhouette and colours of our rasterisation of the file posed by the
    glTF skinning equation (`export.gltf_read`). (Colour fidelity on a colourful mesh: test_export_gltf.py.)"""
    from fixtures.three_view import ThreeView, agreement, our_view, three_or_skip

    from avatarctl.export.gltf_read import pose_glb, read_skinned_glb
    from avatarctl.stages.common import load_fitted, open_fitted

    modules = three_or_skip()
    out = _ground_export(toy_fitted_project)
    A = np.array(json.loads((out / "export.json").read_text())["glb_frame"])
    cap = load_fitted(open_fitted(toy_fitted_project, None), "cpu", None).capture
    camera = _in_file_frame(cap.cameras[cap.split.test_views[0]], A, scale=2.0)
    data = read_skinned_glb(out / "avatar.glb")
    fps = cap.motion.fps if cap.motion.fps > 0 else 30.0
    keys = [0, data.animation_frames[0] - 1]
    times = [(cap.motion.frame_index[k] - cap.motion.frame_index[0]) / fps for k in keys]
    magenta = (1.0, 0.0, 1.0)  # a background no body pixel has
    shots = []
    with ThreeView(out / "avatar.glb", camera.width, camera.height, modules, magenta) as view:
        for key, seconds in zip(keys, times):
            img, info = view.show(seconds, camera)
            assert info["skinned_meshes"] == 1 and info["bones"] == 2 and info["has_colour"], info
            assert info["material"] == "MeshBasicMaterial", "KHR_materials_unlit: the colours are not lit again"
            assert info["lowest_y"] == pytest.approx(pose_glb(data, 0, key)[:, 1].min(), abs=1e-4)
            iou, diff, pixels = agreement(img, our_view(data, key, camera, magenta), magenta)
            assert pixels > 100 and iou > 0.9 and diff.max() < 3.0, (iou, diff, pixels)
            shots.append(img)
    assert np.abs(shots[0].astype(float) - shots[1].astype(float)).mean() > 1.0, "the animation moves the body"
