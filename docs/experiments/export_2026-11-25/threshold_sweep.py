"""Mesh PSNR against the surface level: frame 0 of a fitted project, 8 mm grid, 4 held-out views (bbox).

    PYTHONPATH=. python docs/experiments/export_2026-11-25/threshold_sweep.py   (reads /tmp/P10, a copy of a fitted synth-small project)
"""
import time, numpy as np
from avatarctl.project import Project
from avatarctl.stages.common import load_fitted, frame_node_state
from avatarctl.export.mesh import extract_mesh, slrf_density, slrf_ray_colour
from avatarctl.export.raster import render_mesh
from avatarctl.evaluate.protocols import ground_truth, bbox_region
from avatarctl.evaluate.metrics import psnr
av = load_fitted(Project.open("/tmp/P10"), "cpu", None)
cap = av.capture; f = 0
one = cap.motion.select(cap.motion.rows_for([f]))
st = frame_node_state(av, one, f, True, "mean", 0)
c = st.centers[0].numpy(); r = av.model.cfg.support_radius
verts = av.body.pose(one).vertices[0].numpy()
for th in (5.0, 10.0, 20.0, 40.0):
    t=time.time(); m, q = extract_mesh(slrf_density(av.model, st), slrf_ray_colour(av.model, st), c, r, 0.008, th); te=time.time()-t
    ps=[]
    for view in cap.split.test_views:
        cam = cap.cameras[view].pinhole(); reg = bbox_region(cam, verts)
        gt = ground_truth(cap.image(view, f), cap.mask(view, f), av.background)
        ps.append(psnr(render_mesh(m, cam, av.background).rgb, gt, reg.mask))
    print(f"threshold {th}: {m.num_vertices} verts, {te:.1f}s, psnr {np.mean(ps):.2f}", np.round(ps, 2), flush=True)
