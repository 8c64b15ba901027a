"""Do an avatar's nodes follow its loose garment? Measured against the capture's ground-truth garment (synth captures,
`CAPTURE/gt/geometry.npz`), over the project's training frames. Two parts (issue 28, docs/fit.md "What holds the
skirt back"):

1. **What node motion could explain** (no model needed): each garment vertex is taken to the canonical space with a
   fixed skinning (the weights of the template vertex nearest to it, as a hull node gets; or the root joint only), the
   vertices are grouped into P patches (farthest point sampling on the first frame's canonical garment), and per frame
   each patch is given its best translation (what a node's Delta n can do, Eq. 3) or its best rigid motion
   (Kabsch, onto the patch's Procrustes mean shape). The residual, centimetres (mean and 90th percentile of the per-vertex distances), is what the Gaussians'
   own per-frame offsets would still have to carry.
2. **What the fitted nodes do**: for every node within 3 cm of the garment at the first training frame (posed with
   its learned Delta n), the garment vertex nearest to it there; over the training frames, the spread (distance from its mean) of that vertex's offset
   in the node's frame (A_i^-1 (x - n_i)), with the learned Delta n (latent mean) and with Delta n = 0 (the skeleton
   alone). A node that follows the cloth has a small spread.

    python -m benchmarks.garment_tracking PROJECT [--patches 32,64,128] [--json OUT.json]
"""

from __future__ import annotations

import argparse
import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch


@dataclass(frozen=True)
class PatchResidual:
    skinning: str  # "nearest vertex" | "root"
    patches: int
    translation_cm: float  # residual after each patch's best per-frame translation (mean over vertices and frames)
    translation_p90_cm: float
    rigid_cm: float  # residual after each patch's best per-frame rigid motion
    rigid_p90_cm: float


@dataclass(frozen=True)
class NodeDrift:
    motion: str  # "learned" (Delta n of the latent mean) | "skeleton" (Delta n = 0)
    mean_cm: float
    p90_cm: float


@dataclass(frozen=True)
class TrackingReport:
    frames: int
    garment_vertices: int
    nodes_on_garment: int  # nodes within 3 cm of the garment at the first training frame
    residuals: tuple[PatchResidual, ...]
    drift: tuple[NodeDrift, ...]


def _canonical(points: torch.Tensor, weights: torch.Tensor, joints: torch.Tensor) -> torch.Tensor:
    """points [F, P, 3] world, weights [P, J], joints [F, J, 4, 4] -> [F, P, 3] through the inverse blended transform."""
    T = torch.einsum("pj,fjab->fpab", weights, joints)
    h = torch.cat([points, torch.ones_like(points[..., :1])], -1)
    return (torch.linalg.inv(T) @ h[..., None])[..., :3, 0]


def _kabsch(X: torch.Tensor, Y: torch.Tensor) -> torch.Tensor:
    """X [p, 3], Y [F, p, 3], both centred -> [F, 3, 3] the rotations R minimising sum |Y - R X|^2."""
    U, _, Vh = torch.linalg.svd(torch.einsum("pi,fpj->fij", X, Y))
    d = torch.sign(torch.linalg.det(Vh.transpose(1, 2) @ U.transpose(1, 2)))
    D = torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), d], -1))
    return Vh.transpose(1, 2) @ D @ U.transpose(1, 2)


def patch_residuals(canon: torch.Tensor, patch: torch.Tensor, patches: int, rounds: int = 3
                    ) -> tuple[torch.Tensor, torch.Tensor]:
    """canon [F, P, 3] canonical garment vertices per frame, patch [P] in [0, patches) -> per-vertex residuals [F, P]
    (metres) after each patch's best translation onto each frame (of the patch's mean shape) and after its best
    rigid motion (of the patch's Procrustes mean shape, `rounds` rounds of generalised Procrustes analysis: a
    static texture that turns with the patch)."""
    trans = torch.zeros(canon.shape[:2], dtype=canon.dtype)
    rigid = torch.zeros_like(trans)
    for k in range(patches):
        m = patch == k
        if not m.any():
            continue
        Y = canon[:, m] - canon[:, m].mean(1, keepdim=True)  # [F, p, 3]
        X = Y.mean(0)
        trans[:, m] = (Y - X).norm(dim=-1)
        for _ in range(rounds):
            R = _kabsch(X, Y)
            X = torch.einsum("fji,fpj->fpi", R, Y).mean(0)  # the frames turned back onto X, averaged
        R = _kabsch(X, Y)
        rigid[:, m] = (Y - torch.einsum("fij,pj->fpi", R, X)).norm(dim=-1)
    return trans, rigid


def nodes_on_garment(centers: torch.Tensor, garment: torch.Tensor, near: float = 0.03) -> torch.Tensor:
    """[M] indices of the nodes (centers [F, N, 3]) within `near` metres of the garment (garment [F, P, 3]) at frame 0."""
    from scipy.spatial import cKDTree

    dist, _ = cKDTree(garment[0].numpy()).query(centers[0].numpy())
    return torch.as_tensor(np.flatnonzero(dist < near))


def node_drift(centers: torch.Tensor, linear: torch.Tensor, garment: torch.Tensor, on: torch.Tensor) -> torch.Tensor:
    """centers [F, N, 3] posed nodes, linear [F, N, 3, 3] their A_i, garment [F, P, 3], nodes `on` [M] -> the spread
    [M, F] (metres) of each node's garment vertex (the nearest at frame 0) in the node's frame around its mean."""
    from scipy.spatial import cKDTree

    _, vert = cKDTree(garment[0].numpy()).query(centers[0, on].numpy())
    v = torch.as_tensor(vert).reshape(-1)
    off = (torch.linalg.inv(linear[:, on]) @ (garment[:, v] - centers[:, on])[..., None])[..., 0]  # [F, M, 3]
    return (off - off.mean(0)).norm(dim=-1).T


def measure(project_dir: str | Path, patch_counts: tuple[int, ...] = (32, 64, 128)) -> TrackingReport:
    from scipy.spatial import cKDTree

    from avatarctl.fit.checkpoint import load_avatar
    from avatarctl.io.gt_geometry import find_gt_geometry, load_gt_geometry
    from avatarctl.model.deformer import farthest_point_sampling
    from avatarctl.project import Project

    project = Project.open(project_dir)
    path = find_gt_geometry(project.manifest.source.path)
    if path is None:
        raise SystemExit(f"{project.manifest.source.path} has no gt/geometry.npz: a capture made by `avatarctl synth`")
    gt = load_gt_geometry(path)
    av = load_avatar(project, device="cpu")
    frames = list(av.capture.split.train_frames)
    garment = torch.as_tensor(np.stack([gt.garment_vertices[gt.row(f)] for f in frames]), dtype=torch.float64)
    cond = av.conditioning(av.capture.motion.select(frames), frames_are_training=True)
    posed = av.body.pose(av.capture.motion.select(av.capture.motion.rows_for(frames)))
    joints = posed.joint_transforms.double()  # [F, J, 4, 4]
    W = av.template.skin_weights.double()
    # the fixed skinning of each garment vertex: the canonical template vertex nearest to it at the first frame
    _, v0 = cKDTree(posed.vertices[0].double().numpy()).query(garment[0].numpy())
    start = _canonical(garment[:1], W[torch.as_tensor(v0)], joints[:1])[0]
    _, vfix = cKDTree(av.template.vertices.double().numpy()).query(start.numpy())
    root = torch.zeros(len(vfix), W.shape[1], dtype=W.dtype)
    root[:, 0] = 1.0
    residuals = []
    for name, w in (("nearest vertex", W[torch.as_tensor(vfix)]), ("root", root)):
        canon = _canonical(garment, w, joints)
        for n in patch_counts:
            n = min(n, garment.shape[1])
            centre = start[farthest_point_sampling(start, n, seed=0)]
            patch = torch.cdist(start, centre).argmin(1)
            t, r = patch_residuals(canon, patch, n)
            residuals.append(PatchResidual(name, n, float(t.mean() * 100), float(t.quantile(0.9) * 100),
                                           float(r.mean() * 100), float(r.quantile(0.9) * 100)))
    m = av.model
    with torch.no_grad():
        state = m.node_state(cond, mode="mean")
    T = state.transforms.double()
    skeleton = (T[..., :3, :3] @ m.node_rest.double()[None, :, :, None])[..., 0] + T[..., :3, 3]
    on = nodes_on_garment(state.centers.double(), garment)
    drift = []
    for name, centers in (("learned", state.centers.double()), ("skeleton", skeleton)):
        spread = node_drift(centers, T[..., :3, :3], garment, on)
        drift.append(NodeDrift(name, float(spread.mean() * 100) if len(on) else float("nan"),
                               float(spread.quantile(0.9) * 100) if len(on) else float("nan")))
    return TrackingReport(frames=len(frames), garment_vertices=int(garment.shape[1]), nodes_on_garment=len(on),
                          residuals=tuple(residuals), drift=tuple(drift))


def main(argv: list[str] | None = None) -> TrackingReport:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("project")
    ap.add_argument("--patches", default="32,64,128", help="patch counts, comma list")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    report = measure(args.project, tuple(int(x) for x in args.patches.split(",")))
    print(f"{report.frames} training frames, {report.garment_vertices} garment vertices (CAPTURE/gt/geometry.npz)")
    print("residual of the garment's canonical motion after each patch's best per-frame motion, cm (mean / p90):")
    print(f"  {'skinning':<15} {'patches':>7}  {'translation':>15}  {'rigid':>15}")
    for r in report.residuals:
        print(f"  {r.skinning:<15} {r.patches:>7}  {r.translation_cm:6.2f} / {r.translation_p90_cm:6.2f}  "
              f"{r.rigid_cm:6.2f} / {r.rigid_p90_cm:6.2f}")
    print(f"spread of the garment in the frames of the {report.nodes_on_garment} nodes on it, cm (mean / p90):")
    for d in report.drift:
        print(f"  {d.motion:<9} {d.mean_cm:6.2f} / {d.p90_cm:6.2f}")
    if args.json is not None:
        args.json.write_text(json.dumps(asdict(report), indent=1))
    return report


if __name__ == "__main__":
    main()
