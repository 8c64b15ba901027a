"""export/mesh.py and export/raster.py against an analytic sphere: surface position, outward normals and winding,
baked colours, floaters dropped, no-surface error; the rasterised mesh covers the sphere's silhouette."""

from __future__ import annotations

import numpy as np
import pytest

from avatarctl.export.mesh import (ColouredMesh, NoSurfaceError, bake_colours, density_grid, extract_mesh,
                                   head_on_bake, marching_cubes)

RADIUS = 0.25


def sphere_density(points: np.ndarray) -> np.ndarray:
    """100/m inside a sphere of RADIUS, smooth 5 mm edge; a small blob (a floater) at x = 0.45."""
    r = np.linalg.norm(points, axis=-1)
    blob = np.linalg.norm(points - np.array([0.45, 0.0, 0.0]), axis=-1)
    from scipy.special import expit

    return 100.0 * expit((RADIUS - r) / 0.005) + 100.0 * expit((0.02 - blob) / 0.005)


def colour_by_height(origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Opaque: the colour of the point 2 cm along the ray, red = height; alpha 1 (composited over black)."""
    p = origins + 0.02 * dirs
    rgb = np.stack([np.clip(p[:, 2] / RADIUS * 0.5 + 0.5, 0, 1), np.full(len(p), 0.25), np.full(len(p), 0.75)], -1)
    return rgb * 0.8, np.full(len(p), 0.8)  # alpha 0.8: bake_colours divides it out


CENTERS = np.array([[0.0, 0.0, 0.0], [0.45, 0.0, 0.0]])
HEIGHT_BAKE = head_on_bake(colour_by_height, offset=0.02)  # 2 voxels of 1 cm outside, no background: rgb / alpha


def test_sphere_surface_normals_winding_and_colours():
    mesh, queried = extract_mesh(sphere_density, HEIGHT_BAKE, CENTERS, radius=0.3, voxel=0.01, threshold=50.0)
    r = np.linalg.norm(mesh.vertices, axis=-1)
    assert np.abs(r - RADIUS).max() < 0.005, "vertices on the 50/m level set (the sphere's edge)"
    assert (np.einsum("vi,vi->v", mesh.normals, mesh.vertices / r[:, None]) > 0.95).all(), "outward normals"
    tri = mesh.vertices[mesh.faces].astype(np.float64)
    volume = np.einsum("fi,fi->f", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6.0
    assert volume == pytest.approx(4 / 3 * np.pi * RADIUS ** 3, rel=0.03), "counter-clockwise from outside"
    assert r.max() < 0.3, "the floater (0.2 % of the faces) was dropped"
    expected_red = np.clip(mesh.vertices[:, 2] / RADIUS * 0.5 + 0.5, 0, 1)  # 2 cm in along -n: z scaled by 0.92
    assert np.abs(mesh.colours[:, 0] - expected_red).max() < 0.06
    assert np.allclose(mesh.colours[:, 1:], [0.25, 0.75], atol=1e-5), "alpha divided out"
    grid_points = np.prod(np.ceil((np.array([1.05, 0.6, 0.6]) + 0.02) / 0.01) + 1)
    assert 0 < queried < grid_points, "only points inside a node support are queried"


def test_coarse_to_fine_grid_matches_the_full_grid_where_it_matters():
    full = density_grid(sphere_density, CENTERS, radius=0.3, voxel=0.01)
    fast = density_grid(sphere_density, CENTERS, radius=0.3, voxel=0.01, level=50.0, coarse=2)
    assert fast.queried < 0.7 * full.queried
    n = tuple(min(a, b) for a, b in zip(full.sigma.shape, fast.sigma.shape))
    a, b = full.sigma[:n[0], :n[1], :n[2]], fast.sigma[:n[0], :n[1], :n[2]]
    assert np.array_equal(a > 50.0, b > 50.0), "the same inside / outside everywhere"
    v_full, _, _ = marching_cubes(full, 50.0)
    v_fast, _, _ = marching_cubes(fast, 50.0)
    assert len(v_full) == len(v_fast) and np.abs(np.sort(np.linalg.norm(v_full, axis=-1))
                                                 - np.sort(np.linalg.norm(v_fast, axis=-1))).max() < 1e-5


def test_min_component_zero_keeps_the_floater_and_no_surface_raises():
    grid = density_grid(sphere_density, CENTERS, radius=0.3, voxel=0.01)
    verts, _, _ = marching_cubes(grid, 50.0, min_component=0.0)
    assert np.linalg.norm(verts - [0.45, 0, 0], axis=-1).min() < 0.03
    with pytest.raises(NoSurfaceError, match="never reaches the threshold 500"):
        marching_cubes(grid, 500.0)
    with pytest.raises(ValueError, match="too large"):
        density_grid(sphere_density, CENTERS, radius=0.3, voxel=0.01, max_points=1000)


def test_bake_colours_black_where_nothing_is_hit():
    out = bake_colours(lambda o, d: (np.zeros((len(o), 3)), np.zeros(len(o))), np.zeros((5, 3)),
                       np.tile([0, 0, 1.0], (5, 1)), offset=0.01)
    assert out.shape == (5, 3) and not out.any()


def test_rasterised_mesh_matches_the_sphere_silhouette():
    pytest.importorskip("warp")
    from avatarctl.export.raster import render_mesh
    from avatarctl.geometry.cameras import Camera, look_at

    mesh, _ = extract_mesh(sphere_density, HEIGHT_BAKE, CENTERS[:1], radius=0.3, voxel=0.01, threshold=50.0)
    R, T = look_at(np.array([0.0, -2.0, 0.0]), np.zeros(3))
    cam = Camera("c", K=np.array([[80.0, 0, 31.5], [0, 80.0, 31.5], [0, 0, 1]]), R=R, T=T, width=64, height=64)
    img = render_mesh(mesh, cam, (0.0, 0.0, 0.0))
    yy, xx = np.mgrid[:64, :64]
    inside = np.hypot(xx - 31.5, yy - 31.5) < 80.0 * RADIUS / np.sqrt(4 - RADIUS ** 2) - 1.0
    outside = np.hypot(xx - 31.5, yy - 31.5) > 80.0 * RADIUS / np.sqrt(4 - RADIUS ** 2) + 1.0
    assert img.alpha[inside].all() and not img.alpha[outside].any()
    assert np.allclose(img.rgb[inside][:, 1:], [0.25, 0.75], atol=1e-3)
    assert isinstance(mesh, ColouredMesh)


def test_bake_over_a_background_is_what_the_volume_shows():
    """A half-transparent field (alpha 0.8): the colour baked over a background is the composite, not rgb / alpha."""
    v, n = np.zeros((3, 3)), np.tile([0, 0, 1.0], (3, 1))
    shown = bake_colours(colour_by_height, v, n, offset=0.01, background=(0.0, 0.0, 1.0))
    rgb, alpha = colour_by_height(v + 0.01 * n, -n)
    assert np.allclose(shown, rgb + 0.2 * np.array([0.0, 0.0, 1.0]), atol=1e-6)


def test_body_level_from_the_density_inside_the_skin():
    """The level is a quantile of the density 1 cm inside a body mesh (here a 20 cm sphere inside the 25 cm one:
    100/m there), capped at the ceiling; an empty field is a NoSurfaceError."""
    from avatarctl.export.mesh import body_level

    trimesh = pytest.importorskip("trimesh")
    body = trimesh.creation.icosphere(subdivisions=2, radius=0.2)
    faint = lambda p: 0.04 * sphere_density(p)  # noqa: E731 - 4/m inside
    assert body_level(faint, body.vertices, body.faces) == pytest.approx(4.0, rel=1e-3)
    assert body_level(sphere_density, body.vertices, body.faces) == 10.0, "capped at the default level"
    with pytest.raises(NoSurfaceError, match="inside the body is 0"):
        body_level(lambda p: np.zeros(len(p)), body.vertices, body.faces)


