"""export/view_colours.py against analytic renders: the cameras frame the mesh, the vertices take the colours the
images show of them (a height ramp), a sphere hidden behind another in a view takes none of its colour, pixels the
field leaves nearly empty give none, and unseen vertices take their nearest seen neighbour's colour."""

from __future__ import annotations

import numpy as np
import pytest

from avatarctl.export.view_colours import surround_cameras, view_colours, view_colouring
from avatarctl.geometry.cameras import Camera

UP = np.array([0.0, 0.0, 1.0])


def sphere_mesh(centre, radius: float, subdivisions: int = 3):
    trimesh = pytest.importorskip("trimesh")
    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    v = (np.asarray(s.vertices) + np.asarray(centre)).astype(np.float32)
    return v, np.asarray(s.faces, np.int32), np.asarray(s.vertex_normals, np.float32)


def ray_spheres(cam: Camera, spheres):
    """Per pixel: (index of the first sphere hit or -1, hit point [H*W, 3]) of exact ray-sphere intersections."""
    from avatarctl.synth.raster import camera_rays

    rays = camera_rays(cam)
    d = rays.dirs.reshape(-1, 3).astype(np.float64)
    o = rays.origin.astype(np.float64)
    best_t, which = np.full(len(d), np.inf), np.full(len(d), -1)
    for i, (c, r) in enumerate(spheres):
        oc = o - np.asarray(c, np.float64)
        b = d @ oc
        disc = b * b - (oc @ oc - r * r)
        t = -b - np.sqrt(np.maximum(disc, 0.0))
        hit = (disc > 0) & (t > 0) & (t < best_t)
        best_t[hit], which[hit] = t[hit], i
    return which, o + np.where(np.isfinite(best_t), best_t, 0.0)[:, None] * d


def sphere_render(centre, radius: float, shade):
    """A `ViewRenderFn` of one sphere: shade(hit points [P, 3], hit [P] bool) -> (rgb premultiplied [P, 3], alpha
    [P]) per pixel."""

    def render(cam: Camera):
        which, p = ray_spheres(cam, [(centre, radius)])
        rgb, alpha = shade(p, which >= 0)
        return rgb.reshape(cam.height, cam.width, 3).astype(np.float32), \
            alpha.reshape(cam.height, cam.width).astype(np.float32)

    return render


def test_cameras_surround_and_frame_the_mesh():
    v, _, _ = sphere_mesh([0.3, -0.2, 1.0], 0.4)
    cams = surround_cameras(v, UP, count=20, size=64, distance=3.0, pole=0.9)
    assert len(cams) == 18, "the 2 directions within acos(0.9) of the up axis are skipped"
    heights = []
    for cam in cams:
        p = v @ cam.R.T + cam.T
        uv = p[:, :2] / p[:, 2:] * cam.K[0, 0] + cam.K[0, 2]
        assert (p[:, 2] > 0).all() and (uv > -0.5).all() and (uv < 63.5).all(), "every vertex in every image"
        assert uv.max() - uv.min() > 0.9 * 64, "the sphere fills the image"
        heights.append(float((cam.center - [0.3, -0.2, 1.0]) @ UP))
    assert min(heights) < -0.5 and max(heights) > 0.5, "from below and from above"
    with pytest.raises(ValueError, match="distance"):
        surround_cameras(v, UP, distance=0.9)


def test_vertices_take_the_colours_the_images_show():
    """A sphere whose rendered colour is a ramp in height: each vertex gets the ramp at its own height."""
    pytest.importorskip("warp")
    centre, radius = np.array([0.0, 0.0, 1.0]), 0.3
    v, f, n = sphere_mesh(centre, radius)

    def shade(p, hit):
        ramp = np.clip((p[:, 2] - centre[2]) / radius * 0.5 + 0.5, 0, 1)
        return np.stack([ramp, 1.0 - ramp, np.full_like(ramp, 0.5)], -1) * hit[:, None] * 0.8, 0.8 * hit  # alpha 0.8

    render = sphere_render(centre, radius, shade)

    out = view_colours(v, f, n, render, surround_cameras(v, UP, count=24, size=96))
    expected = np.clip((v[:, 2] - centre[2]) / radius * 0.5 + 0.5, 0, 1)
    assert out.views == 22 and out.seen.mean() > 0.97, "nearly every vertex seen"
    assert np.abs(out.colours[:, 0] - expected).max() < 0.08, "the ramp at each vertex's height (alpha divided out)"
    assert np.allclose(out.colours[:, 2], 0.5, atol=1e-5)
    whole, done = view_colouring(render, UP, count=24, size=96)(v, f, n, np.zeros(len(v), bool))
    assert done.all() and np.allclose(whole, out.colours), "every vertex coloured at once, whatever is asked for"


def test_a_hidden_surface_takes_none_of_the_colour_in_front_of_it():
    """Two spheres side by side, red and blue: from the cameras where one hides part of the other, the hidden part
    must not take the front one's colour (visibility by the mesh's own ray cast)."""
    pytest.importorskip("warp")
    spheres = [(np.array([-0.16, 0.0, 1.0]), 0.15), (np.array([0.16, 0.0, 1.0]), 0.15)]
    parts = [sphere_mesh(c, r) for c, r in spheres]
    v = np.concatenate([p[0] for p in parts])
    f = np.concatenate([parts[0][1], parts[1][1] + len(parts[0][0])])
    n = np.concatenate([p[2] for p in parts])
    colour = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])

    def render(cam: Camera):
        which, _ = ray_spheres(cam, spheres)
        rgb = np.where(which[:, None] >= 0, colour[np.maximum(which, 0)], 0.0)
        return rgb.reshape(cam.height, cam.width, 3).astype(np.float32), \
            (which >= 0).reshape(cam.height, cam.width).astype(np.float32)

    out = view_colours(v, f, n, render, surround_cameras(v, UP, count=24, size=96), power=0.0)
    first = np.arange(len(v)) < len(parts[0][0])
    assert out.seen.mean() > 0.9
    # a vertex on a silhouette edge may take a pixel of the other sphere where the two meshes' tessellations
    # disagree with the exact spheres; the colours of the two stay apart
    assert np.median(out.colours[first, 0]) > 0.99 and np.median(out.colours[~first, 2]) > 0.99
    assert (out.colours[first, 0] > 0.8).mean() > 0.97 and (out.colours[~first, 2] > 0.8).mean() > 0.97


def test_nearly_empty_pixels_give_no_colour_and_unseen_vertices_take_the_nearest():
    """The field's alpha is below `min_alpha` on the sphere's upper half: those vertices are unseen and take the
    colour of the nearest seen vertex (the equator's); with nothing seen at all every vertex is black."""
    pytest.importorskip("warp")
    centre, radius = np.array([0.0, 0.0, 0.0]), 0.3
    v, f, n = sphere_mesh(centre, radius)

    def shade(p, hit):
        alpha = np.where(p[:, 2] > 0.05, 0.1, 1.0) * hit
        return np.where(p[:, 2:3] > 0.05, [0.0, 1.0, 0.0], [1.0, 1.0, 1.0]) * alpha[:, None], alpha

    render = sphere_render(centre, radius, shade)

    cams = surround_cameras(v, UP, count=24, size=96)
    out = view_colours(v, f, n, render, cams, min_alpha=0.3)
    top = v[:, 2] > 0.1  # a face straddling z = 0.05 (edges ~4 cm) colours its upper vertex too
    assert not out.seen[top].any() and out.seen[v[:, 2] < 0].all()
    assert np.allclose(out.colours, 1.0, atol=1e-5), "the green of the thin part never shows; nearest seen: white"
    none = view_colours(v, f, n, lambda c: (np.zeros((96, 96, 3), np.float32), np.zeros((96, 96), np.float32)), cams)
    assert not none.seen.any() and not none.colours.any()
