"""export/skinning.py and export/gltf.py: quaternions, pivots, weight transfer, and a skinned animated .glb read back
by independent readers (pygltflib, trimesh, the Khronos validator) and posed from the file's data against our LBS;
linear vertex colours in glTF, sRGB bytes in PLY."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from avatarctl.body.lbs import axis_angle_to_matrix, forward_kinematics, lbs
from avatarctl.export import skinning
from avatarctl.export.gltf import Animation, SkinnedMesh, glb_bytes, linear_to_srgb, srgb_to_linear, write_mesh
from avatarctl.export.mesh import ColouredMesh

PARENTS = (-1, 0, 1)
REST_JOINTS = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.4], [0.0, 0.0, 0.8]])


def chain(frames: int = 6, seed: int = 0):
    """A 3-joint chain (z up), a box mesh along it, weights by height, a random animation (rigid M_j)."""
    g = torch.Generator().manual_seed(seed)
    rot = axis_angle_to_matrix(0.6 * torch.randn(frames, 3, 3, generator=g, dtype=torch.float64))
    M = forward_kinematics(rot, torch.from_numpy(REST_JOINTS), PARENTS,
                           root_translation=0.1 * torch.randn(frames, 3, generator=g, dtype=torch.float64))
    zs = np.linspace(0.0, 1.0, 11)
    ring = np.array([[0.1, 0.1], [-0.1, 0.1], [-0.1, -0.1], [0.1, -0.1]])
    verts = np.array([[x, y, z] for z in zs for x, y in ring])
    faces = []
    for k in range(len(zs) - 1):
        for i in range(4):
            a, b, c, d = 4 * k + i, 4 * k + (i + 1) % 4, 4 * (k + 1) + (i + 1) % 4, 4 * (k + 1) + i
            faces += [[a, b, c], [a, c, d]]
    w = np.stack([np.clip(1 - np.abs(verts[:, 2] - j) / 0.4, 0, None) for j in (0.0, 0.4, 0.8)], -1) + 1e-3
    w /= w.sum(-1, keepdims=True)
    mesh = ColouredMesh(vertices=verts.astype(np.float32), faces=np.array(faces, np.int32),
                        normals=np.tile(np.float32([1, 0, 0]), (len(verts), 1)),
                        colours=np.full((len(verts), 3), 0.5, np.float32))
    return mesh, w.astype(np.float32), M.numpy()


def pivots_of(mesh, w, M) -> np.ndarray:
    """[J, 3] joint centres as the export takes them (body/joints.py)."""
    from avatarctl.body.joints import joint_centres, skin_weighted_centroids

    fallback = skin_weighted_centroids(torch.from_numpy(mesh.vertices).double(), torch.from_numpy(w))
    return joint_centres(torch.from_numpy(M), PARENTS, fallback).numpy()


CAPS = np.array([[0, 2, 1], [0, 3, 2], [40, 41, 42], [40, 42, 43]], np.int32)  # close the chain's tube (outward)


def skinned_glb(tmp_path, basis=np.eye(3), influences=4, weights=None, colours=None, closed=False):
    mesh, w, M = chain()
    w = w if weights is None else weights
    mesh = mesh if colours is None else replace(mesh, colours=colours)
    mesh = replace(mesh, faces=np.concatenate([mesh.faces, CAPS])) if closed else mesh
    mesh_y = replace(mesh, vertices=(mesh.vertices @ basis.T).astype(np.float32))
    pivots = pivots_of(mesh, w, M) @ basis.T
    M_y = skinning.conjugate(M, basis)
    sw = skinning.sparsify(w, influences)
    ibm = np.tile(np.eye(4), (3, 1, 1))
    ibm[:, :3, 3] = -pivots
    trs = skinning.local_trs(skinning.joint_globals(M_y, pivots), PARENTS)
    skin = SkinnedMesh(weights=sw, joint_names=("a", "b", "c"), parents=PARENTS,
                       pose=skinning.rest_trs(pivots, PARENTS), inverse_bind=ibm)
    path = tmp_path / "chain.glb"
    path.write_bytes(glb_bytes(mesh_y, skin, (Animation("walk", np.arange(M.shape[0]) / 30.0, trs),)))
    return path, mesh_y, sw, M_y, trs


def test_quaternion_round_trip_and_up_basis():
    R = axis_angle_to_matrix(torch.randn(200, 3, dtype=torch.float64) * 2).numpy()
    R[0] = np.diag([1.0, -1.0, -1.0])  # 180 degrees: the w ~ 0 branch
    q = skinning.matrix_to_quaternion(R)
    assert np.allclose(skinning.quaternion_to_matrix(q), R, atol=1e-12)
    for up in ([0, 0, 1.0], [0, -1.0, 0], [0.3, 0.2, 0.9]):
        C = skinning.up_to_y_basis(np.array(up))
        assert np.allclose(C @ (np.array(up) / np.linalg.norm(up)), [0, 1, 0]) and np.isclose(np.linalg.det(C), 1)


def test_joint_centres_give_exact_local_trs_and_fixed_bones():
    mesh, w, M = chain()
    piv = pivots_of(mesh, w, M)
    assert np.abs(piv[1:] - REST_JOINTS[1:]).max() < 1e-4, "the point moving with both bones is the joint"
    trs = skinning.local_trs(skinning.joint_globals(M, piv), PARENTS)
    assert trs.residual < 1e-9 and np.allclose(trs.scale, 1.0, atol=1e-9)
    assert np.allclose(trs.translation[:, 1:], piv[1:] - piv[:-1], atol=1e-4), "bones of (nearly) fixed length"


def test_transfer_and_sparsify_weights():
    tpl = np.array([[0, 0, 0.0], [1, 0, 0], [0, 1, 0]])
    tw = np.eye(3)[:, :3] * 0.7 + 0.1
    dense = skinning.transfer_weights(np.array([[0, 0, 0.0], [0.5, 0.5, 0]]), tpl, tw, k=2)
    assert np.allclose(dense.sum(-1), 1) and np.allclose(dense[0], tw[0], atol=1e-4)
    sw = skinning.sparsify(np.array([[0.5, 0.2, 0.15, 0.1, 0.05]], np.float32))
    assert sw.joints.tolist() == [[0, 1, 2, 3]] and sw.dense_residual == pytest.approx(0.05)
    assert np.allclose(sw.dense(5), [[0.5 / 0.95, 0.2 / 0.95, 0.15 / 0.95, 0.1 / 0.95, 0]])
    two = skinning.sparsify(np.array([[0.25, 0.75]], np.float32))  # fewer joints than influences: zero padding
    assert np.allclose(two.dense(2), [[0.25, 0.75]])
    zeros = skinning.sparsify(np.array([[0.0, 0.0, 0.6, 0.0, 0.4, 0.0]], np.float32))
    assert zeros.joints.tolist() == [[2, 4, 0, 0]] and np.allclose(zeros.weights, [[0.6, 0.4, 0, 0]]), \
        "an unused influence has joint 0 (glTF)"


@pytest.mark.parametrize("basis, influences", [(np.eye(3), 4), (skinning.up_to_y_basis(np.array([0, 0, 1.0])), 4),
                                               (np.eye(3), 8)])
def test_skinned_glb_read_back_and_posed_matches_our_lbs(tmp_path, basis, influences):
    pytest.importorskip("pygltflib")
    from avatarctl.export.gltf_read import pose_glb, read_skinned_glb

    path, mesh_y, sw, M_y, trs = skinned_glb(tmp_path, basis, influences)
    data = read_skinned_glb(path)
    assert data.joints.shape == (44, influences) and data.weights.shape == (44, influences)
    assert data.positions.shape == (44, 3) and data.faces.shape == (80, 3) and data.animation_frames[0] == 6
    assert np.abs(pose_glb(data) - mesh_y.vertices).max() < 1e-6, "rest pose = the exported mesh"
    ours = lbs(torch.from_numpy(mesh_y.vertices.astype(np.float64)), torch.from_numpy(sw.dense(3).astype(np.float64)),
               torch.from_numpy(M_y)).numpy()
    for f in range(M_y.shape[0]):
        assert np.abs(pose_glb(data, 0, f) - ours[f]).max() < 1e-5, f"frame {f}"


def test_glb_loads_in_trimesh_and_static_formats(tmp_path):
    trimesh = pytest.importorskip("trimesh")
    path, mesh_y, *_ = skinned_glb(tmp_path)
    scene = trimesh.load(str(path), force="scene")
    geom = list(scene.geometry.values())[0]
    assert geom.vertices.shape == (44, 3) and geom.faces.shape == (80, 3)
    colour = np.asarray(geom.visual.vertex_attributes["color"])  # trimesh keeps COLOR_0 as stored: linear
    assert np.allclose(colour[:, :3] / (255.0 if colour.dtype.kind in "iu" else 1.0), srgb_to_linear(0.5),
                       atol=1 / 255)
    mesh, _, _ = chain()
    for ext in ("glb", "ply", "obj"):
        write_mesh(tmp_path / f"m.{ext}", mesh)
        back = trimesh.load(str(tmp_path / f"m.{ext}"), force="mesh", process=False)
        assert back.vertices.shape == (44, 3) and back.faces.shape == (80, 3), ext
        assert np.allclose(back.vertices, mesh.vertices, atol=1e-6), ext
    with pytest.raises(ValueError, match="unknown mesh format"):
        write_mesh(tmp_path / "m.stl", mesh)
    with pytest.raises(ValueError, match="needs a skin"):
        glb_bytes(mesh, None, (Animation("a", np.zeros(1), skinning.rest_trs(REST_JOINTS, PARENTS)),))


def test_srgb_curve():
    assert srgb_to_linear(np.array([0.0, 0.04045, 0.5, 1.0])) == pytest.approx([0.0, 0.04045 / 12.92, 0.21404, 1.0],
                                                                               abs=1e-5)
    x = np.linspace(0, 1, 1001)
    assert np.abs(linear_to_srgb(srgb_to_linear(x)) - x).max() < 1e-12
    assert np.all(np.diff(srgb_to_linear(x)) > 0)


def test_glb_colours_are_linear_and_ply_bytes_srgb(tmp_path):
    """What a glTF viewer shows (COLOR_0 encoded for the screen) is the mesh's colour; a PLY holds its sRGB bytes."""
    pygltflib = pytest.importorskip("pygltflib")
    mesh, _, _ = chain()
    rng = np.random.default_rng(0)
    mesh = replace(mesh, colours=rng.uniform(0, 1, mesh.colours.shape).astype(np.float32))
    write_mesh(tmp_path / "m.glb", mesh)
    g = pygltflib.GLTF2().load(str(tmp_path / "m.glb"))
    acc = g.accessors[g.meshes[0].primitives[0].attributes.COLOR_0]
    view = g.bufferViews[acc.bufferView]
    stored = np.frombuffer(g.binary_blob(), np.float32, acc.count * 3, view.byteOffset or 0).reshape(-1, 3)
    assert np.abs(stored - srgb_to_linear(mesh.colours)).max() < 1e-6, "COLOR_0 is linear light"
    assert np.abs(linear_to_srgb(stored) - mesh.colours).max() < 1e-5, "displayed = the baked (volume) colour"
    trimesh = pytest.importorskip("trimesh")
    write_mesh(tmp_path / "m.ply", mesh)
    ply = trimesh.load(str(tmp_path / "m.ply"), process=False)
    assert np.abs(ply.visual.vertex_colors[:, :3] / 255.0 - mesh.colours).max() <= 0.5 / 255 + 1e-6


@pytest.mark.node
def test_khronos_validator_zero_errors_and_warnings(tmp_path):
    """The Khronos glTF validator (npm gltf-validator, no issue limit) on a static mesh and on a skinned, animated
    avatar whose weights have exact zeros (unused influences)."""
    from fixtures.node import npm_modules, validate_gltf

    if npm_modules() is None:
        pytest.skip("no node / npm, or npm could not install gltf-validator")
    mesh, w, _ = chain()
    w = np.where(w < 0.01, 0.0, w)  # most vertices now have 1-2 joints, the rest of the 4 slots unused
    w /= w.sum(-1, keepdims=True)
    path, *_ = skinned_glb(tmp_path, weights=w.astype(np.float32))
    write_mesh(tmp_path / "static.glb", mesh)
    for p in (path, tmp_path / "static.glb"):
        report = validate_gltf(p)
        assert report["errors"] == 0 and report["warnings"] == 0, (p.name, report)


@pytest.mark.browser
@pytest.mark.node
def test_three_js_shows_the_baked_colours(tmp_path):
    """The chain, olive below and skin-coloured above (sRGB), in three.js (GLTFLoader, sRGB output): at two
    animation times its pixels have the baked colours (within 3 levels of our rasterisation of the file, and the
    median pixel within 2 levels of a palette colour; a file holding sRGB in COLOR_0 shows the olive 80 levels too
    bright) and the images differ."""
    from fixtures.three_view import ThreeView, agreement, our_view, three_or_skip

    from avatarctl.export.gltf_read import read_skinned_glb
    from avatarctl.geometry.cameras import Camera, look_at

    modules = three_or_skip()
    palette = np.array([[112, 114, 87], [224, 172, 140]], np.float32) / 255.0  # an olive top, skin
    ring = (np.repeat(np.arange(11), 4) >= 6).astype(int)
    path, *_ = skinned_glb(tmp_path, skinning.up_to_y_basis(np.array([0, 0, 1.0])), colours=palette[ring],
                              closed=True)  # a viewer culls back faces (the file is single-sided); we do not
    data = read_skinned_glb(path)
    R, T = look_at(np.array([0.0, 0.3, 1.6]), np.array([0.0, 0.3, 0.0]), np.array([0.0, 1.0, 0.0]))
    camera = Camera("front", K=np.array([[320.0, 0, 119.5], [0, 320.0, 119.5], [0, 0, 1]]), R=R, T=T, width=240,
                    height=240)
    magenta = (1.0, 0.0, 1.0)
    shots = []
    with ThreeView(path, camera.width, camera.height, modules, magenta) as view:
        for key in (0, 5):
            img, info = view.show(key / 30.0, camera)
            assert info["skinned_meshes"] == 1 and info["bones"] == 3 and info["animations"] == 1, info
            ours = our_view(data, key, camera, magenta)
            iou, diff, pixels = agreement(img, ours, magenta)
            assert pixels > 300 and iou > 0.9 and diff.max() < 3.0, (iou, diff, pixels)
            body = np.abs(img.astype(int) - [255, 0, 255]).max(-1) > 0
            nearest = np.abs(img[body][:, None].astype(float) - palette[None] * 255).max(-1).min(-1)
            assert np.median(nearest) <= 2.0, "the pixels are the palette's sRGB colours"
            shots.append(img)
    assert np.abs(shots[0].astype(float) - shots[1].astype(float)).mean() > 1.0, "the animation moves the chain"
