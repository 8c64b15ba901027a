"""What the training masks show beyond the body, per capture: the persistent off-body cells of the hull-node
survey (avatarctl/fit/hull_nodes.py) with the carve before 2026-11-25 (every hull voxel) and now (only voxels some
view shows where the posed body does not), split by the body part of the nearest canonical vertex, with the median
distance of the cells to the canonical mesh, the share of the mask pixels outside the posed body's silhouette
(grown by 2 px; mean over the surveyed frames x training views), and what `model.hull_nodes=auto` decides.

    python docs/experiments/hull_auto_2026-11-25/survey.py PROJECT [PROJECT ...]
"""

from __future__ import annotations

import sys

import numpy as np
import torch
from scipy.spatial import cKDTree

from avatarctl.body.registry import load_body_model
from avatarctl.fit.hull_nodes import auto_hull_nodes, survey_hull
from avatarctl.io.project_io import load_project_capture
from avatarctl.model import ModelConfig
from avatarctl.model.deformer import farthest_point_sampling
from avatarctl.project import Project

PARTS = (("arm", ("arm", "hand", "shoulder", "clavicle", "elbow", "wrist", "finger", "thumb", "index", "middle",
                  "ring", "pinky", "collar")),
         ("leg", ("leg", "thigh", "knee", "foot", "toe", "ankle", "calf", "hip")),
         ("head", ("head", "neck", "jaw", "eye")))


def part(name: str) -> str:
    n = name.lower()
    return next((p for p, keys in PARTS if any(k in n for k in keys)), "torso")


def unexplained_share(cap, body, tpl, frames: list[int], views: list[str], max_frames: int = 24) -> float:
    """Mean share of the mask pixels outside the posed body's silhouette grown by 2 px (the survey's frames)."""
    import cv2

    from avatarctl.geometry.silhouette import rasterize_silhouette

    use = [frames[i] for i in np.unique(np.linspace(0, len(frames) - 1, min(max_frames, len(frames))).astype(int))]
    posed = body.pose(cap.motion.select(cap.motion.rows_for(use)))
    shares = []
    for t, frame in enumerate(use):
        for v in views:
            sil = rasterize_silhouette(cap.cameras[v], posed.vertices[t].numpy(), tpl.faces.numpy(), supersample=1)
            sil = cv2.dilate(sil.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
            mask = cap.mask(v, frame)
            shares.append((mask & ~sil).sum() / max(1, mask.sum()))
    return float(np.mean(shares))


def main(projects: list[str]) -> None:
    cfg = ModelConfig.preset("cpu")
    k = cfg.hull_auto_nodes
    print("| capture | training views | mask pixels the body does not explain | carve | persistent off-body cells | "
          "litres | % of body | leg / torso / arm / head cells | median distance to the mesh | auto decides |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for path in projects:
        cap = load_project_capture(Project.open(path))
        body = load_body_model(cap.body_model, cap.body_model_path)
        tpl = body.template(cap.motion)
        frames, views = sorted(int(f) for f in cap.split.train_frames), list(cap.split.train_views)
        surface = farthest_point_sampling(tpl.vertices, cfg.num_nodes - k, 0)
        vpart = np.array([part(tpl.joint_names[j]) for j in tpl.skin_weights.argmax(1).tolist()])
        unexplained = 100 * unexplained_share(cap, body, tpl, frames, views)
        tree = cKDTree(tpl.vertices.detach().double().numpy())
        for label, px in (("every hull voxel", None), ("unexplained by the body (2 px)", 2)):
            s = survey_hull(cap, body, tpl, frames, views, surface, cfg.hull_min_dist, explain_px=px)
            dist, nearest = tree.query(s.cells) if len(s.cells) else (np.zeros(0), np.zeros(0, dtype=int))
            parts = vpart[nearest]
            split = " / ".join(str(int((parts == p).sum())) for p in ("leg", "torso", "arm", "head"))
            k_auto = auto_hull_nodes(s, k, cfg.hull_auto_min_volume)
            median = f"{np.median(dist):.2f} m" if len(dist) else "—"
            print(f"| {path} | {len(views)} | {unexplained:.1f} % | {label} | {len(s.cells):,} | {s.volume * 1e3:.1f} | "
                  f"{100 * s.share:.1f} | {split} | {median} | {f'{k_auto} hull nodes' if k_auto else 'none'} |")


if __name__ == "__main__":
    torch.set_num_threads(1)
    main(sys.argv[1:])
