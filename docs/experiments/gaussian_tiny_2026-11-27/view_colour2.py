"""Probe: the product's export.view_colours with its knobs, vs the head-on bake, on one project's export surface.
python view_colour2.py PROJECT LEVEL [--frames 0,8,16,28] [--count 44] [--size 384] [--power 4] [--amin 0.3] [--dist 3]
"""
import argparse, time
import numpy as np
from avatarctl.project import Project
from avatarctl.fit.checkpoint import load_avatar
from avatarctl.stages.common import frame_node_state
from avatarctl.render.trajectories import up_from_cameras
from avatarctl.export.mesh import ColouredMesh, extract_mesh, head_on_bake, slrf_density, slrf_ray_colour
from avatarctl.export.raster import render_mesh
from avatarctl.export.view_colours import gaussian_views, surround_cameras, view_colours
from avatarctl.evaluate.metrics import psnr
from avatarctl.evaluate.protocols import bbox_region, ground_truth

ap = argparse.ArgumentParser()
ap.add_argument("project"); ap.add_argument("level", type=float)
ap.add_argument("--frames", default="0,8,16,28")
ap.add_argument("--count", type=int, default=44); ap.add_argument("--size", type=int, default=384)
ap.add_argument("--power", type=float, default=4.0); ap.add_argument("--amin", type=float, default=0.3)
ap.add_argument("--aw", type=float, default=0.0, help="weight pixels by alpha**aw")
ap.add_argument("--dist", type=float, default=3.0); ap.add_argument("--pole", type=float, default=0.9)
a = ap.parse_args()
import avatarctl.export.view_colours as VC
if a.aw:
    _orig_bary = VC.barycentric
    import inspect
    src = inspect.getsource(VC.view_colours).replace("w = bc * (cos ** power)[:, None]", "w = bc * (cos ** power * a ** AW)[:, None]")
    ns = dict(VC.__dict__); ns["AW"] = a.aw
    exec(src, ns)
    view_colours = ns["view_colours"]
av = load_avatar(Project.open(a.project)); cap = av.capture
bg = tuple(float(x) for x in av.background)
up = up_from_cameras(list(cap.cameras.values()))
res = {"bake": [], "views": []}; tc = []
for frame in [int(x) for x in a.frames.split(",")]:
    one = cap.motion.select(cap.motion.rows_for([frame]))
    is_train = frame in set(av.train_frames)
    state = frame_node_state(av, one, frame, is_train, "mean" if is_train else "novel", 0)
    mesh, _ = extract_mesh(slrf_density(av.model, state), head_on_bake(slrf_ray_colour(av.model, state), 0.016, bg),
                           state.centers[0].detach().float().cpu().numpy(), float(av.model.cfg.support_radius), 0.008,
                           a.level, 0.01)
    t1 = time.perf_counter()
    cams = surround_cameras(mesh.vertices, up, a.count, a.size, a.dist, a.pole)
    vc = view_colours(mesh.vertices, mesh.faces, mesh.normals, gaussian_views(av.model, state), cams, a.power, a.amin)
    tc.append(time.perf_counter() - t1)
    vmesh = ColouredMesh(vertices=mesh.vertices, faces=mesh.faces, normals=mesh.normals, colours=vc.colours)
    body = av.body.pose(one).vertices[0].detach().float().cpu().numpy()
    for view in cap.split.test_views:
        cam = cap.cameras[view].pinhole()
        region = bbox_region(cam, body)
        gt = ground_truth(cap.image(view, frame), cap.mask(view, frame), av.background)
        for key, m in (("bake", mesh), ("views", vmesh)):
            res[key].append(psnr(render_mesh(m, cam, av.background).rgb, gt, region.mask))
print(f"{vars(a)}\nbake {np.mean(res['bake']):.3f}  views {np.mean(res['views']):.3f}  (n={len(res['bake'])}) colour {np.mean(tc):.1f} s/mesh")
