"""Figures of the export note: the exported meshes seen by a held-out camera, and avatar.glb posed from the file.

    python docs/experiments/export_2026-11-25/make_figures.py PROJECT OUT_DIR

Reads PROJECT/export/default (written by `avatarctl export PROJECT --frames 0,40 --score`), writes into OUT_DIR:
- `posed_meshes.png`: per exported frame, ground truth | volume render | posed mesh (unlit baked colours), the first
  held-out camera, cropped to the eval box;
- `skinned_frames.png`: avatar.glb read back with pygltflib and posed from its own joints, weights and animation
  (`export.gltf_read.pose_glb`) at four animation keyframes, rotated back to the capture frame and rasterised with
  its baked colours, beside the ground truth of that frame;
- `figures.json`: the numbers behind them (file sizes, reload errors, PSNRs).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np


def main(project: Path, out: Path) -> None:
    from avatarctl.evaluate.metrics import psnr
    from avatarctl.evaluate.protocols import bbox_region, ground_truth
    from avatarctl.export.gltf_read import pose_glb, read_skinned_glb
    from avatarctl.export.mesh import ColouredMesh
    from avatarctl.export.raster import render_mesh
    from avatarctl.fit.checkpoint import load_avatar
    from avatarctl.project import Project
    from avatarctl.render.engine import render_view
    from avatarctl.stages.common import frame_node_state

    out.mkdir(parents=True, exist_ok=True)
    proj = Project.open(project)
    exp = proj.paths.export("default")
    rec = json.loads((exp / "export.json").read_text())
    av = load_avatar(proj, device="cpu")
    cap = av.capture
    view = cap.split.test_views[0]
    cam = cap.cameras[view].pinhole()
    C = np.asarray(rec["glb_basis"])  # capture world -> glTF (+Y up)
    figures = {"export": {k: rec[k] for k in ("meshes", "avatar", "score_mean", "timing")}}

    def gt_box(frame: int):
        one = cap.motion.select(cap.motion.rows_for([frame]))
        region = bbox_region(cam, av.body.pose(one).vertices[0].numpy())
        return one, region, ground_truth(cap.image(view, frame), cap.mask(view, frame), av.background)

    rows = []
    for m in rec["meshes"]:
        frame = m["frame"]
        data = read_static_glb(exp / f"meshes/{frame:06d}.glb")
        mesh = ColouredMesh(vertices=(data[0] @ C).astype(np.float32), faces=data[1],
                            normals=np.zeros_like(data[0], np.float32), colours=data[2].astype(np.float32))
        one, region, gt = gt_box(frame)
        state = frame_node_state(av, one, frame, frame in av.train_frames, m["latent"], 0)
        vol = render_view(av.model, state, 0, cam, av.background).rgb
        mimg = render_mesh(mesh, cam, av.background).rgb
        rows.append(np.concatenate([region.crop_image(x) for x in (gt, vol, mimg)], axis=1))
    _write(out / "posed_meshes.png", _stack(rows))

    skinned = read_skinned_glb(exp / "avatar.glb")
    n = skinned.animation_frames[0]
    frames = [int(f) for f in np.linspace(0, n - 1, 4).round()]
    tiles, scores = [], []
    for k in frames:
        v = pose_glb(skinned, 0, k) @ C  # back to the capture frame
        mesh = ColouredMesh(vertices=v.astype(np.float32), faces=skinned.faces.astype(np.int32),
                            normals=np.zeros_like(v, np.float32), colours=skinned.colours[:, :3].astype(np.float32))
        frame = int(cap.motion.frame_index[k])
        _, region, gt = gt_box(frame)
        img = render_mesh(mesh, cam, av.background).rgb
        scores.append({"animation_frame": k, "capture_frame": frame, "view": view,
                       "psnr_skinned_mesh": psnr(img, gt, region.mask)})
        tiles.append(np.concatenate([region.crop_image(gt), region.crop_image(img)], axis=1))
    _write(out / "skinned_frames.png", _stack(tiles))
    figures["skinned_frames"] = scores
    (out / "figures.json").write_text(json.dumps(figures, indent=2))


def read_static_glb(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(positions [verts, 3], faces [faces, 3], colours [verts, 3] in [0, 1]) of a posed .glb, read with trimesh."""
    import trimesh

    scene = trimesh.load(str(path), force="scene", process=False)
    geom = list(scene.geometry.values())[0]
    c = np.asarray(geom.visual.vertex_attributes["color"])  # our COLOR_0 (trimesh keeps it beside the material)
    colours = c[:, :3].astype(np.float64) / (255.0 if c.dtype.kind in "iu" else 1.0)
    return np.asarray(geom.vertices, np.float64), np.asarray(geom.faces, np.int32), colours


def _stack(rows: list[np.ndarray]) -> np.ndarray:
    w = max(r.shape[1] for r in rows)
    return np.concatenate([np.pad(r, ((0, 0), (0, w - r.shape[1]), (0, 0))) for r in rows], axis=0)


def _write(path: Path, rgb: np.ndarray) -> None:
    from avatarctl.render.images import write_png

    write_png(path, rgb, None)


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]))
