"""glTF 2.0 binary (.glb) writer for coloured meshes, skinned meshes and joint animations; numpy only.

What a file holds (glTF 2.0 spec names):
- one mesh primitive: POSITION, NORMAL (float32 VEC3), COLOR_0 (float32 VEC3), uint32 indices;
  COLOR_0 is linear light (glTF 2.0 spec 3.7.2.1: "vertex colors ... in linear space"): the mesh's colours are
  display (sRGB-encoded) values, like the images the field was fitted to, and are decoded with `srgb_to_linear`;
  a conforming viewer encodes them back for the screen and shows the volume render's colour. PLY / OBJ bytes stay
  sRGB (what those formats' readers display as is);
  an unlit material (`KHR_materials_unlit`: the colours are baked radiance, a viewer must not light them again);
- with a skin (`SkinnedMesh`): JOINTS_0 (uint16 VEC4), WEIGHTS_0 (float32 VEC4) (and JOINTS_1 / WEIGHTS_1 with 8
  influences per vertex), one node per joint (its own TRS:
  the pose a viewer shows without playing an animation; the joint tree as node children), `skins[0]` with `inverseBindMatrices` (float32 MAT4, column-major) and the
  mesh node that references it;
- with an `Animation`: one LINEAR sampler per joint for translation and rotation (and scale when any differs from
  1), keyframe times in seconds.

Units metres; glTF is +Y up: callers pass geometry already in that frame (`skinning.up_to_y_basis`).
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from avatarctl.export.mesh import ColouredMesh
from avatarctl.export.skinning import JointTrs, SkinWeights

GENERATOR = "avatarctl export"


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """sRGB-encoded values in [0, 1] -> linear light (IEC 61966-2-1, the piecewise curve, not a 2.2 power)."""
    c = np.clip(np.asarray(c, np.float64), 0.0, 1.0)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(c: np.ndarray) -> np.ndarray:
    """Linear light in [0, 1] -> sRGB-encoded values (the inverse of `srgb_to_linear`; what a viewer shows)."""
    c = np.clip(np.asarray(c, np.float64), 0.0, 1.0)
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * c ** (1 / 2.4) - 0.055)


@dataclass(frozen=True)
class SkinnedMesh:
    """What a skinned glTF needs besides the mesh (all in the file's frame)."""

    weights: SkinWeights  # [verts, 4 | 8] joints / weights
    joint_names: tuple[str, ...]  # [J]
    parents: tuple[int, ...]  # [J], -1 = root; parents precede children
    pose: JointTrs  # one frame: the joint nodes' own local TRS (shown without animation; the bind pose, or a frame)
    inverse_bind: np.ndarray  # [J, 4, 4] B_j^-1 (row-major here, written column-major)


@dataclass(frozen=True)
class Animation:
    name: str
    times: np.ndarray  # [frames] seconds, increasing
    trs: JointTrs  # [frames, J, ...] local joint transforms


class _Builder:
    """Accumulates the binary buffer and the JSON of one .glb."""

    def __init__(self) -> None:
        self.blob = bytearray()
        self.views: list[dict] = []
        self.accessors: list[dict] = []

    def add(self, array: np.ndarray, component: int, kind: str, target: int | None = None,
            minmax: bool = False, normalized: bool = False) -> int:
        """Append `array` (already in its component dtype) as a bufferView + accessor; -> accessor index."""
        data = np.ascontiguousarray(array).tobytes()
        while len(self.blob) % 4:
            self.blob.append(0)
        view = {"buffer": 0, "byteOffset": len(self.blob), "byteLength": len(data)}
        if target is not None:
            view["target"] = target
        self.blob += data
        self.views.append(view)
        count = int(array.shape[0])
        acc = {"bufferView": len(self.views) - 1, "componentType": component, "count": count, "type": kind}
        if normalized:
            acc["normalized"] = True
        if minmax:
            flat = array.reshape(count, -1).astype(np.float64)
            acc["min"] = flat.min(0).tolist() if count else [0.0] * flat.shape[1]
            acc["max"] = flat.max(0).tolist() if count else [0.0] * flat.shape[1]
        self.accessors.append(acc)
        return len(self.accessors) - 1


FLOAT, UINT, USHORT = 5126, 5125, 5123
ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963


def glb_bytes(mesh: ColouredMesh, skin: SkinnedMesh | None = None, animations: tuple[Animation, ...] = ()) -> bytes:
    """The .glb file content (module docstring)."""
    if animations and skin is None:
        raise ValueError("an animation needs a skin (its channels drive the joint nodes)")
    b = _Builder()
    attrs = {"POSITION": b.add(mesh.vertices.astype(np.float32), FLOAT, "VEC3", ARRAY_BUFFER, minmax=True),
             "NORMAL": b.add(mesh.normals.astype(np.float32), FLOAT, "VEC3", ARRAY_BUFFER),
             "COLOR_0": b.add(srgb_to_linear(mesh.colours).astype(np.float32), FLOAT, "VEC3", ARRAY_BUFFER)}
    nodes: list[dict] = []
    scene_nodes: list[int] = []
    gltf: dict = {"asset": {"version": "2.0", "generator": GENERATOR},
                  "extensionsUsed": ["KHR_materials_unlit"],
                  "materials": [{"name": "baked", "pbrMetallicRoughness": {"baseColorFactor": [1, 1, 1, 1],
                                                                            "metallicFactor": 0.0,
                                                                            "roughnessFactor": 1.0},
                                 "extensions": {"KHR_materials_unlit": {}}}]}
    if skin is not None:
        J = len(skin.parents)
        n = skin.weights.joints.shape[1]
        assert skin.weights.joints.shape == (mesh.num_vertices, n) and n in (4, 8), f"joints {skin.weights.joints.shape}"
        for k in range(n // 4):
            cols = slice(4 * k, 4 * k + 4)
            attrs[f"JOINTS_{k}"] = b.add(skin.weights.joints[:, cols].astype(np.uint16), USHORT, "VEC4", ARRAY_BUFFER)
            attrs[f"WEIGHTS_{k}"] = b.add(skin.weights.weights[:, cols].astype(np.float32), FLOAT, "VEC4",
                                          ARRAY_BUFFER)
        children: list[list[int]] = [[] for _ in range(J)]
        for j, p in enumerate(skin.parents):
            if p >= 0:
                children[p].append(j)
            else:
                scene_nodes.append(j)
        for j in range(J):
            node = {"name": skin.joint_names[j],
                    "translation": [float(x) for x in skin.pose.translation[0, j]],
                    "rotation": [float(x) for x in skin.pose.rotation[0, j]]}
            if not np.allclose(skin.pose.scale[0, j], 1.0, atol=1e-6):
                node["scale"] = [float(x) for x in skin.pose.scale[0, j]]
            if children[j]:
                node["children"] = children[j]
            nodes.append(node)
        ibm = np.ascontiguousarray(np.swapaxes(skin.inverse_bind.astype(np.float32), -1, -2))  # column-major
        gltf["skins"] = [{"name": "body", "joints": list(range(J)), "skeleton": scene_nodes[0],
                          "inverseBindMatrices": b.add(ibm, FLOAT, "MAT4")}]
    indices = b.add(mesh.faces.astype(np.uint32).reshape(-1), UINT, "SCALAR", ELEMENT_ARRAY_BUFFER)
    gltf["meshes"] = [{"name": "avatar", "primitives": [{"attributes": attrs, "indices": indices, "material": 0,
                                                         "mode": 4}]}]
    mesh_node = {"name": "avatar", "mesh": 0}
    if skin is not None:
        mesh_node["skin"] = 0
    nodes.append(mesh_node)
    scene_nodes.append(len(nodes) - 1)
    gltf["nodes"] = nodes
    gltf["scenes"] = [{"nodes": scene_nodes}]
    gltf["scene"] = 0
    if animations:
        gltf["animations"] = [_animation(b, a) for a in animations]
    gltf["accessors"] = b.accessors
    gltf["bufferViews"] = b.views
    gltf["buffers"] = [{"byteLength": len(b.blob)}]
    return _pack(gltf, bytes(b.blob))


def _animation(b: _Builder, anim: Animation) -> dict:
    times = np.asarray(anim.times, np.float32)
    F, J = anim.trs.translation.shape[:2]
    assert times.shape == (F,) and F >= 1, f"times {times.shape} vs {F} frames"
    t_acc = b.add(times, FLOAT, "SCALAR", minmax=True)
    samplers: list[dict] = []
    channels: list[dict] = []
    with_scale = not np.allclose(anim.trs.scale, 1.0, atol=1e-5)
    for j in range(J):
        paths = [("translation", anim.trs.translation[:, j], "VEC3"), ("rotation", anim.trs.rotation[:, j], "VEC4")]
        if with_scale:
            paths.append(("scale", anim.trs.scale[:, j], "VEC3"))
        for path, values, kind in paths:
            samplers.append({"input": t_acc, "output": b.add(values.astype(np.float32), FLOAT, kind),
                             "interpolation": "LINEAR"})
            channels.append({"sampler": len(samplers) - 1, "target": {"node": j, "path": path}})
    return {"name": anim.name, "samplers": samplers, "channels": channels}


def _pack(gltf: dict, blob: bytes) -> bytes:
    js = json.dumps(gltf, separators=(",", ":")).encode("utf-8")
    js += b" " * (-len(js) % 4)
    blob += b"\0" * (-len(blob) % 4)
    total = 12 + 8 + len(js) + 8 + len(blob)
    return (struct.pack("<4sII", b"glTF", 2, total) + struct.pack("<I4s", len(js), b"JSON") + js
            + struct.pack("<I4s", len(blob), b"BIN\0") + blob)


def write_mesh(path: Path, mesh: ColouredMesh) -> None:
    """One coloured mesh as .glb (this module), .ply or .obj (trimesh, the `export` extra); not atomic (callers
    write into a temporary directory)."""
    path = Path(path)
    if path.suffix == ".glb":
        path.write_bytes(glb_bytes(mesh))
        return
    try:
        import trimesh
    except ImportError:
        raise ImportError("writing .ply / .obj needs trimesh: pip install 'avatarctl[export]' (or use --format glb)") \
            from None
    colours = (np.clip(mesh.colours, 0, 1) * 255 + 0.5).astype(np.uint8)
    tm = trimesh.Trimesh(vertices=mesh.vertices, faces=mesh.faces, vertex_normals=mesh.normals,
                         vertex_colors=colours, process=False)
    if path.suffix == ".ply":
        path.write_bytes(tm.export(file_type="ply", encoding="binary"))
    elif path.suffix == ".obj":
        path.write_text(tm.export(file_type="obj", include_color=True, include_normals=True))
    else:
        raise ValueError(f"unknown mesh format {path.suffix!r}; use .glb, .ply or .obj")
