"""export/level.py: the surface level chosen by training images, on a soft analytic ball whose photographs show a ball
of a known radius: the search finds the level of that radius (up and down the ladder), scores each candidate once,
and hands back the same mesh `extract_mesh` makes at that level; the stage records the candidates."""

from __future__ import annotations

import json

import numpy as np
import pytest

from avatarctl.export.level import (LEVEL_STEP, ScoringImage, choose_level, pick_views, scoring_image,
                                    search_steps)
from avatarctl.export.mesh import density_grid, extract_mesh, head_on_bake
from avatarctl.geometry.cameras import Camera, look_at

FALLOFF = 0.05  # metres: sigma(r) = 100 exp(-r / FALLOFF), so the level L is the ball of radius FALLOFF ln(100 / L)
RED = np.array([0.8, 0.2, 0.2])
BASE = 5.0  # the "body level" handed to the chooser, 1/metre
CENTERS = np.zeros((1, 3))


def soft_ball(points: np.ndarray) -> np.ndarray:
    return 100.0 * np.exp(-np.linalg.norm(points, axis=-1) / FALLOFF)


def opaque_red(origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return np.tile(RED, (len(origins), 1)), np.ones(len(origins))


RED_BAKE = head_on_bake(opaque_red, offset=0.02, background=(0.0, 0.0, 0.0))


def radius_of(level: float) -> float:
    return FALLOFF * np.log(100.0 / level)


def photographs(radius: float) -> list[ScoringImage]:
    """Two 48 x 48 views of a red ball of `radius` over black (exact ray-sphere hits), the whole image scored."""
    from avatarctl.synth.raster import camera_rays

    out = []
    for name, eye in (("front", [0.0, -1.2, 0.0]), ("side", [1.2, 0.0, 0.3])):
        R, T = look_at(np.array(eye), np.zeros(3))
        cam = Camera(name, K=np.array([[60.0, 0, 23.5], [0, 60.0, 23.5], [0, 0, 1]]), R=R, T=T, width=48, height=48)
        rays = camera_rays(cam)
        d = rays.dirs.reshape(-1, 3).astype(np.float64)
        b = d @ rays.origin
        hit = b * b - (rays.origin @ rays.origin - radius ** 2) > 0
        img = np.where(hit[:, None], RED, 0.0).reshape(48, 48, 3).astype(np.float32)
        out.append(ScoringImage(view=name, camera=cam, target=img, region=np.ones((48, 48), bool)))
    return out


@pytest.mark.parametrize("best", [-2, 1])
def test_the_chooser_finds_the_level_the_photographs_show(best):
    pytest.importorskip("warp")
    true_level = BASE * LEVEL_STEP ** best
    grid = density_grid(soft_ball, CENTERS, radius=0.3, voxel=0.01, level=BASE)
    choice, mesh = choose_level(grid, BASE, RED_BAKE, photographs(radius_of(true_level)), (0.0, 0.0, 0.0))
    tried = [c.step for c in choice.candidates]
    expected = [0, -1, 1, -2, -3] if best == -2 else [0, -1, 1, 2]
    assert tried == expected, "k = 0 and its neighbours, then the climb until the score falls (each scored once)"
    assert choice.step == best and choice.level == pytest.approx(true_level, abs=1e-4)
    assert choice.factor == pytest.approx(LEVEL_STEP ** best) and choice.views == ("front", "side")
    scores = {c.step: c.psnr for c in choice.candidates}
    assert scores[best] == max(scores.values()) and scores[best] > 30.0
    assert all(0 < c.baked < c.faces for c in choice.candidates), "only the vertices the views see are baked"
    plain, _ = extract_mesh(soft_ball, RED_BAKE, CENTERS, radius=0.3, voxel=0.01, threshold=BASE * LEVEL_STEP ** best)
    assert np.array_equal(mesh.faces, plain.faces) and np.allclose(mesh.vertices, plain.vertices, atol=1e-6)
    assert np.allclose(mesh.colours, plain.colours, atol=1e-6), "every vertex baked, as extract_mesh does"


def test_a_level_without_surface_loses_and_none_at_all_raises():
    pytest.importorskip("warp")
    from avatarctl.export.mesh import NoSurfaceError

    def flat_top(points: np.ndarray) -> np.ndarray:
        return np.minimum(soft_ball(points), 50.0)  # no surface above 50/m

    grid = density_grid(flat_top, CENTERS, radius=0.3, voxel=0.01, level=40.0)
    choice, _ = choose_level(grid, 40.0, RED_BAKE, photographs(radius_of(40.0 / LEVEL_STEP)), (0.0, 0.0, 0.0))
    assert [(c.step, c.psnr is None) for c in choice.candidates] == [(0, False), (-1, False), (1, True), (-2, False)]
    assert choice.step == -1
    with pytest.raises(NoSurfaceError, match="no candidate level"):
        choose_level(grid, 1e4, RED_BAKE, photographs(0.1), (0.0, 0.0, 0.0))


@pytest.mark.parametrize("peak, steps, expected, scored", [
    (3, 4, 3, [0, -1, 1, 2, 3, 4]),
    (-9, 4, -4, [0, -1, 1, -2, -3, -4]),  # the ladder's end
    (0, 4, 0, [0, -1, 1]),
    (0.4, 4, 0, [0, -1, 1]),  # the neighbour must beat k = 0
    (2, 0, 0, [0]),
])
def test_search_steps_climbs_to_the_peak_and_stops(peak, steps, expected, scored):
    calls = []

    def score(k: int) -> float:
        calls.append(k)
        return -abs(k - peak)

    assert search_steps(score, steps) == expected and calls == scored


def test_pick_views_spreads_and_scoring_images_are_bounded():
    assert pick_views(["a", "b", "c", "d", "e", "f"]) == ["a", "c", "f"] and pick_views(["a", "b"]) == ["a", "b"]
    R, T = look_at(np.array([0.0, -2.0, 0.0]), np.zeros(3))
    cam = Camera("big", K=np.array([[500.0, 0, 255.5], [0, 500.0, 191.5], [0, 0, 1]]), R=R, T=T, width=512,
                 height=384)
    rgb = np.full((384, 512, 3), 255, np.uint8)
    mask = np.zeros((384, 512), np.float32)
    mask[:, :256] = 1.0  # left half: white photograph; right half: the background
    body = np.array([[-0.2, 0.0, -0.3], [0.2, 0.0, 0.3]])
    im = scoring_image("big", cam, rgb, mask, (0.0, 0.0, 1.0), body, max_side=256)
    assert (im.camera.width, im.camera.height) == (256, 192) and im.target.shape == (192, 256, 3)
    assert np.allclose(im.target[:, :127], 1.0) and np.allclose(im.target[:, 129:], [0.0, 0.0, 1.0])
    assert im.region.any() and not im.region.all(), "the body's bbox in the scaled camera"
    small = scoring_image("big", cam, rgb, mask, (0.0, 0.0, 1.0), body, max_side=1024)
    assert small.camera.width == 512 and small.target.shape == (384, 512, 3)


def test_export_auto_level_records_the_candidates(toy_fitted_project):
    from avatarctl.stages import export
    from avatarctl.stages.export import ExportConfig

    res = export.run(toy_fitted_project, ExportConfig(name="auto", frames="3,0", formats=("glb",), voxel=0.03,
                                                      device="cpu"))
    lv = res.level
    assert lv is not None and lv.frame == 0, "the first posed training frame (3 is a test frame)"
    c = lv.choice
    scores = {s.step: s.psnr for s in c.candidates if s.psnr is not None}
    assert scores[c.step] == max(scores.values())
    for k in (c.step - 1, c.step + 1):  # the search stopped where both neighbours are worse (or the ladder ends)
        assert k not in scores or scores[k] < scores[c.step]
    by_frame = {m.frame: m for m in res.meshes}
    assert by_frame[0].threshold == pytest.approx(c.level, abs=1e-3)
    assert all(m.pieces >= 1 and 0 < m.largest_piece <= 1 for m in res.meshes)
    rec = json.loads((res.out_dir / "export.json").read_text())["level_choice"]
    assert rec["frame"] == 0 and rec["level"] == c.level and len(rec["candidates"]) == len(c.candidates)
    assert {"level", "psnr", "faces", "pieces", "largest_piece", "baked", "step"} <= set(rec["candidates"][0])
    fixed = export.run(toy_fitted_project, ExportConfig(name="fixed", frames="0", formats=("glb",), voxel=0.03,
                                                        threshold=0.3, device="cpu"))
    assert fixed.level is None
    assert json.loads((fixed.out_dir / "export.json").read_text())["level_choice"] is None
