"""Probe: a Gaussian avatar's posed mesh by fusing rendered depth (TSDF) instead of marching its density.

python depth_fuse.py PROJECT FRAME [--views 48] [--voxel 0.008] [--trunc 0.02] [--size 256]
Scores the mesh like `avatarctl export --score` (held-out views, bbox PSNR, unlit vertex colours).
"""
import argparse
import time

import numpy as np
import torch

from avatarctl.project import Project
from avatarctl.fit.checkpoint import load_avatar
from avatarctl.stages.common import frame_node_state
from avatarctl.geometry.cameras import Camera, look_at
from avatarctl.render.trajectories import up_from_cameras
from avatarctl.splat import render_gaussians
from avatarctl.splat.camera import SplatCamera
from avatarctl.export.mesh import ColouredMesh, DensityGrid, marching_cubes, bake_colours, vertex_normals
from avatarctl.stages.export import _field
from avatarctl.export.raster import render_mesh
from avatarctl.evaluate.metrics import psnr
from avatarctl.evaluate.protocols import bbox_region, ground_truth

ap = argparse.ArgumentParser()
ap.add_argument("project")
ap.add_argument("frame", type=int)
ap.add_argument("--views", type=int, default=48)
ap.add_argument("--voxel", type=float, default=0.008)
ap.add_argument("--trunc", type=float, default=0.02)
ap.add_argument("--size", type=int, default=256)
ap.add_argument("--alpha", type=float, default=0.5)
ap.add_argument("--carve", type=int, default=1)
ap.add_argument("--depth", default="mean", choices=["mean", "median"])
ap.add_argument("--planes", type=int, default=64)
ap.add_argument("--radius", type=float, default=2.5)
ap.add_argument("--geometry", default="tsdf", choices=["tsdf", "density"])
ap.add_argument("--level", type=float, default=0.0)
ap.add_argument("--tol", type=float, default=0.015)
ap.add_argument("--colour", default="bake", choices=["bake", "views"])
a = ap.parse_args()

t0 = time.perf_counter()
av = load_avatar(Project.open(a.project))
cap = av.capture
one = cap.motion.select(cap.motion.rows_for([a.frame]))
is_train = a.frame in set(av.train_frames)
state = frame_node_state(av, one, a.frame, is_train, "mean" if is_train else "novel", 0)
with torch.no_grad():
    posed = av.model.posed_gaussians(state)
means, covars, opac = posed.means[0].float(), posed.covars[0].float(), posed.opacities[0].float()
keep = opac > 0.0
body = av.body.pose(one).vertices[0].detach().float().cpu().numpy()
centre = body.mean(0)
up = up_from_cameras([cap.cameras[v] for v in cap.cameras])
height = float((body @ up).max() - (body @ up).min())
radius = a.radius * height
f = a.size * 1.2  # ~45 degree field of view
K = np.array([[f, 0, a.size / 2], [0, f, a.size / 2], [0, 0, 1.0]])
# virtual cameras: a Fibonacci sphere around the body (none at the held-out cameras on purpose)
cams = []
n = a.views
for i in range(n):
    z = 1 - 2 * (i + 0.5) / n
    if abs(z) > 0.9:
        continue
    phi = i * np.pi * (3 - np.sqrt(5))
    # build a direction in a frame where `up` is the pole
    e1 = np.cross(up, [1.0, 0, 0]); e1 = e1 / np.linalg.norm(e1) if np.linalg.norm(e1) > 1e-6 else np.cross(up, [0, 1.0, 0])
    e2 = np.cross(up, e1)
    d = z * up + np.sqrt(1 - z * z) * (np.cos(phi) * e1 + np.sin(phi) * e2)
    R, T = look_at(centre + radius * d, centre, up)
    cams.append(Camera(name=f"v{i}", K=K, R=R, T=T, width=a.size, height=a.size))
# render colour + camera depth
depths, alphas, rgbs = [], [], []
with torch.no_grad():
    for c in cams:
        sc = SplatCamera.from_camera(c)
        Rt = torch.tensor(c.R, dtype=torch.float32)
        Tt = torch.tensor(c.T, dtype=torch.float32)
        zc = (means @ Rt.T + Tt)[:, 2:3]
        col = posed.colors(0, sc.center)
        out = render_gaussians(means, covars, torch.cat([col, zc], 1), opac, sc, torch.zeros(4))
        al = out.alpha
        if a.depth == "median":  # where the front splats' alpha crosses 1/2: sweep depth planes over the splat centres
            zs = zc[:, 0]
            planes = torch.linspace(float(zs.min()), float(zs.max()), a.planes)
            prev_a = torch.zeros_like(al)
            med = torch.full_like(al, float("nan"))
            one = torch.ones(len(zs), 1)
            for k, d in enumerate(planes):
                o = torch.where(zs <= d, opac, torch.zeros_like(opac))
                af = render_gaussians(means, covars, one, o, sc, torch.zeros(1)).alpha
                cross = torch.isnan(med) & (af >= 0.5)
                if k > 0:
                    t = ((0.5 - prev_a) / (af - prev_a).clamp(min=1e-6)).clamp(0, 1)
                    med = torch.where(cross, planes[k - 1] + t * (d - planes[k - 1]), med)
                else:
                    med = torch.where(cross, d.expand_as(med), med)
                prev_a = af
            depths.append(torch.nan_to_num(med, nan=1e9).numpy())
        else:
            depths.append((out.rgb[..., 3] / al.clamp(min=1e-6)).numpy())
        alphas.append(al.numpy())
        rgbs.append((out.rgb[..., :3] / al.clamp(min=1e-6)[..., None]).clamp(0, 1).numpy())
t1 = time.perf_counter()
# TSDF over the node supports' box
lo = means.min(0).values.numpy() - 0.05
hi = means.max(0).values.numpy() + 0.05
shape = np.ceil((hi - lo) / a.voxel).astype(int) + 1
g = np.stack(np.meshgrid(*[lo[k] + a.voxel * np.arange(shape[k]) for k in range(3)], indexing="ij"), -1).reshape(-1, 3)
sdf_sum = np.zeros(len(g), np.float32)
w_sum = np.zeros(len(g), np.float32)
empty_votes = np.zeros(len(g), np.float32)
for c, D, A in zip(cams, depths, alphas):
    pc = g @ c.R.T + c.T
    z = pc[:, 2]
    u = np.round(pc[:, 0] / z * c.K[0, 0] + c.K[0, 2]).astype(int)
    v = np.round(pc[:, 1] / z * c.K[1, 1] + c.K[1, 2]).astype(int)
    ok = (z > 0) & (u >= 0) & (u < c.width) & (v >= 0) & (v < c.height)
    idx = np.where(ok)[0]
    al = A[v[idx], u[idx]]
    dd = D[v[idx], u[idx]]
    hit = al > a.alpha
    sdf = dd - z[idx]  # > 0: voxel in front of the surface
    # in front (or silhouette miss): free space votes; behind within trunc: fused
    miss = ~hit
    empty_votes[idx[miss]] += 1
    use = hit & (sdf > -a.trunc)
    s = np.clip(sdf[use] / a.trunc, -1, 1)
    sdf_sum[idx[use]] += s
    w_sum[idx[use]] += 1
tsdf = np.where(w_sum > 0, sdf_sum / np.maximum(w_sum, 1), 1.0)
tsdf = np.where(empty_votes >= a.carve, 1.0, tsdf)  # carved by any silhouette miss
occ = (-tsdf).reshape(*shape).astype(np.float32)  # > 0 inside
grid = DensityGrid(sigma=np.pad(occ, 1, constant_values=-1.0), origin=lo - a.voxel, voxel=a.voxel, queried=0)
density, bake = _field(av, state)
if a.geometry == "density":  # the export's own surface: the density grid refined around the level, marched
    from avatarctl.export.mesh import density_grid
    dg = density_grid(density, state.centers[0].detach().float().cpu().numpy(), float(av.model.cfg.support_radius),
                      a.voxel, level=a.level / 4)
    verts, faces, normals = marching_cubes(dg, a.level, 0.01)
else:
    verts, faces, normals = marching_cubes(grid, 0.0, 0.01)
t2 = time.perf_counter()
if a.colour == "bake":
    colours = bake_colours(bake, verts, normals, 2.0 * a.voxel, tuple(float(x) for x in av.background))
else:  # the rendered views: the most frontal view that sees the vertex unoccluded
    colours = np.zeros((len(verts), 3), np.float32); best = np.full(len(verts), -1.0)
    for c, D, A, C in zip(cams, depths, alphas, rgbs):
        pc = verts @ c.R.T + c.T
        z = pc[:, 2]
        u = np.round(pc[:, 0] / z * c.K[0, 0] + c.K[0, 2]).astype(int).clip(0, c.width - 1)
        v = np.round(pc[:, 1] / z * c.K[1, 1] + c.K[1, 2]).astype(int).clip(0, c.height - 1)
        vis = (np.abs(D[v, u] - z) < a.tol) & (A[v, u] > a.alpha)
        cosang = -(normals * (verts - (-c.R.T @ c.T))).sum(-1) / np.linalg.norm(verts - (-c.R.T @ c.T), axis=-1)
        better = vis & (cosang > best)
        colours[better] = C[v[better], u[better]]
        best[better] = cosang[better]
if a.colour == "views":  # vertices no view saw: the nearest seen vertex's colour
    from scipy.spatial import cKDTree
    seen = best > -1.0
    if (~seen).any() and seen.any():
        _, j = cKDTree(verts[seen]).query(verts[~seen])
        colours[~seen] = colours[seen][j]
    print("unseen vertices", int((~seen).sum()), "of", len(verts))
mesh = ColouredMesh(vertices=verts, faces=faces, normals=normals, colours=colours.astype(np.float32))
t3 = time.perf_counter()
scores = []
for view in cap.split.test_views:
    cam = cap.cameras[view].pinhole()
    region = bbox_region(cam, body)
    gt = ground_truth(cap.image(view, a.frame), cap.mask(view, a.frame), av.background)
    img = render_mesh(mesh, cam, av.background).rgb
    scores.append(psnr(img, gt, region.mask))
    import imageio.v3 as iio
    iio.imwrite(f"fuse_{view}.png", (np.concatenate([gt, img], 1) * 255).astype(np.uint8))
print(f"views {len(cams)} verts {len(verts)} faces {len(faces)} colour {a.colour}: mesh PSNR {np.mean(scores):.2f} "
      f"({', '.join(f'{s:.2f}' for s in scores)}); render {t1 - t0:.1f} s, tsdf+mc {t2 - t1:.1f} s, colour {t3 - t2:.1f} s")
