"""Read a skinned .glb back with an independent parser (pygltflib, the `export` extra) and pose it from the file's
own data: the reload check of `avatarctl export` and the tests.

glTF skinning (spec 3.7.3): posed v = sum_k w_k G_{j_k} B_{j_k}^-1 v, G_j the joint node's global matrix (the
product of local T R S matrices from the scene root), B_j^-1 the inverse bind matrix. Keyframe `frame` of an
animation sets every animated node's TRS to that frame's output values (no interpolation needed at keyframes).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from avatarctl.export.skinning import quaternion_to_matrix

_NUMPY = {5126: np.float32, 5125: np.uint32, 5123: np.uint16, 5121: np.uint8}
_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}


@dataclass(frozen=True)
class GltfSkinned:
    """The data of the first skinned primitive of a .glb, as numpy arrays."""

    positions: np.ndarray  # [verts, 3]
    faces: np.ndarray  # [faces, 3]
    colours: np.ndarray | None  # [verts, 3|4] COLOR_0 as stored: linear light (gltf.linear_to_srgb to display)
    joints: np.ndarray  # [verts, 4 | 8] indices into `skin_joints` (JOINTS_0, then JOINTS_1 when present)
    weights: np.ndarray  # [verts, 4 | 8]
    skin_joints: list[int]  # node index of each skin joint
    inverse_bind: np.ndarray  # [joints, 4, 4] row-major
    nodes: list[dict]  # per node: translation, rotation (x, y, z, w), scale, children
    animations: list[dict[tuple[int, str], np.ndarray]]  # per animation: (node, path) -> [frames, width]
    animation_frames: list[int]


def read_skinned_glb(path: str | Path) -> GltfSkinned:
    try:
        import pygltflib
    except ImportError:
        raise ImportError("reading .glb back needs pygltflib: pip install 'avatarctl[export]'") from None
    g = pygltflib.GLTF2().load(str(path))
    blob = g.binary_blob()

    def arr(i: int) -> np.ndarray:
        a = g.accessors[i]
        v = g.bufferViews[a.bufferView]
        n = _WIDTH[a.type]
        dt = np.dtype(_NUMPY[a.componentType])
        start = (v.byteOffset or 0) + (a.byteOffset or 0)
        out = np.frombuffer(blob, dtype=dt, count=a.count * n, offset=start)
        return out.reshape(a.count, n) if n > 1 else out

    prim = g.meshes[0].primitives[0]
    at = prim.attributes
    joint_sets = [a for a in (at.JOINTS_0, getattr(at, "JOINTS_1", None)) if a is not None]
    weight_sets = [a for a in (at.WEIGHTS_0, getattr(at, "WEIGHTS_1", None)) if a is not None]
    skin = g.skins[0]
    nodes = [{"translation": np.array(n.translation if n.translation else [0, 0, 0], np.float64),
              "rotation": np.array(n.rotation if n.rotation else [0, 0, 0, 1], np.float64),
              "scale": np.array(n.scale if n.scale else [1, 1, 1], np.float64),
              "children": list(n.children or []), "matrix": n.matrix} for n in g.nodes]
    anims, counts = [], []
    for an in g.animations or []:
        ch: dict[tuple[int, str], np.ndarray] = {}
        for c in an.channels:
            s = an.samplers[c.sampler]
            ch[(c.target.node, c.target.path)] = np.asarray(arr(s.output), np.float64)
            counts.append(len(arr(s.input)))
        anims.append(ch)
    return GltfSkinned(positions=np.asarray(arr(at.POSITION), np.float64),
                       faces=np.asarray(arr(prim.indices), np.int64).reshape(-1, 3),
                       colours=np.asarray(arr(at.COLOR_0)) if at.COLOR_0 is not None else None,
                       joints=np.concatenate([np.asarray(arr(i), np.int64) for i in joint_sets], axis=1),
                       weights=np.concatenate([np.asarray(arr(i), np.float64) for i in weight_sets], axis=1),
                       skin_joints=list(skin.joints),
                       inverse_bind=np.swapaxes(arr(skin.inverseBindMatrices).reshape(-1, 4, 4), -1, -2).astype(
                           np.float64),
                       nodes=nodes, animations=anims, animation_frames=counts)


def node_globals(data: GltfSkinned, animation: int | None = None, frame: int = 0) -> np.ndarray:
    """[nodes, 4, 4] global matrices of every node (rest TRS, or keyframe `frame` of `animation`)."""
    N = len(data.nodes)
    local = np.zeros((N, 4, 4))
    for i, n in enumerate(data.nodes):
        t, r, s = n["translation"], n["rotation"], n["scale"]
        if animation is not None:
            ch = data.animations[animation]
            t = ch.get((i, "translation"), t[None].repeat(frame + 1, 0))[frame]
            r = ch.get((i, "rotation"), r[None].repeat(frame + 1, 0))[frame]
            s = ch.get((i, "scale"), s[None].repeat(frame + 1, 0))[frame]
        if n["matrix"] is not None and animation is None:
            local[i] = np.asarray(n["matrix"], np.float64).reshape(4, 4).T
            continue
        local[i] = np.eye(4)
        local[i, :3, :3] = quaternion_to_matrix(r) * np.asarray(s)[None, :]
        local[i, :3, 3] = t
    parent = np.full(N, -1)
    for i, n in enumerate(data.nodes):
        for c in n["children"]:
            parent[c] = i
    out = np.zeros_like(local)
    done = np.zeros(N, bool)

    def world(i: int) -> np.ndarray:
        if not done[i]:
            out[i] = local[i] if parent[i] < 0 else world(parent[i]) @ local[i]
            done[i] = True
        return out[i]

    for i in range(N):
        world(i)
    return out


def pose_glb(data: GltfSkinned, animation: int | None = None, frame: int = 0) -> np.ndarray:
    """[verts, 3] vertices skinned by the file's own data (module docstring)."""
    G = node_globals(data, animation, frame)
    joint_mats = G[data.skin_joints] @ data.inverse_bind  # [joints, 4, 4]
    blended = np.einsum("vk,vkab->vab", data.weights, joint_mats[data.joints])  # [verts, 4, 4]
    return np.einsum("vab,vb->va", blended[:, :3, :3], data.positions) + blended[:, :3, 3]
