"""Do an avatar's nodes follow its loose garment? Measured against the capture's ground-truth garment (synth captures,
`CAPTURE/gt/geometry.npz`), over the project's training frames. Five parts (issue 28, docs/fit.md "Why the skirt
stays a blur"):

1. **What node motion could explain** (no model needed): each garment vertex is taken to the canonical space with a
   fixed skinning (the weights of the template vertex nearest to it, as a hull node gets; or the root joint only), the
   vertices are grouped into P patches (farthest point sampling on the first frame's canonical garment), and per frame
   each patch is given its best translation (what a node's Delta n can do, Eq. 3) or its best rigid motion
   (Kabsch, onto the patch's Procrustes mean shape). The residual, centimetres (mean and 90th percentile of the
   per-vertex distances), is what the Gaussians' own per-frame offsets would still have to carry.
2. **What the fitted nodes do**: for every node within 3 cm of the garment at the first training frame (posed with
   its learned Delta n), the garment vertex nearest to it there; over the training frames, the spread (distance
   from its mean) of that vertex's offset in the node's frame (A_i^-1 (x - n_i)), with the learned Delta n (latent
   mean; "tracked" when the fit placed nodes by its garment tracking, `track`: those nodes by the tracks) and with
   Delta n = 0 (the skeleton alone). A node that follows the cloth has a small spread. Per frame
   (median and p90 over the nodes) and per node (mean over the frames): where the motion loses the cloth.
   Gaussian-field avatars, the cloth as drawn: every garment vertex in the frame of the node whose live Gaussian
   (opacity >= 0.05, posed at the first training frame) is nearest to it, the same spread over all vertices
   (`drawn_drift`): a node near the cloth need not be the one drawing it (a hull node sits in the garment's volume).
3. **Would optical flow tell where the cloth moves?** (`--flow`, no model needed): OpenCV's Farnebäck optical flow
   (pyramid of 4 levels at scale 0.5, window 15, 5 iterations; better here than DIS at any preset: median error 0.55
   px against DIS medium 0.69, fast 1.27, ultrafast 1.30, all with a p90 of 6.6-6.9 px) between
   consecutive training frames of each training view (the ingested, undistorted images), read at the projections of
   the garment vertices that face the camera and lie inside the frame's mask, against those vertices' true projected
   motion: the end-point error in pixels beside the true motion's size. A small error against the motion means the
   flow could supervise the projected motion of the Gaussians.

4. **Do the Gaussians on the garment move with it from frame to frame?** (Gaussian-field avatars): for every 5th
   training frame t whose next frame is a training frame, the Gaussians (opacity >= 0.05, latent mean) within 2 cm of
   the garment at t, in every training view: their projected motion t -> t + 1 against that of their nearest garment
   vertex (end-point error, pixels), beside the garment's projected motion.

6. **Does the fit's garment tracking follow the cloth?** (a fit with `track=true`: `PROJECT/fit/track/tracks.npz`):
   each tracked surface vertex is matched at the reference frame to the nearest point of the true garment surface
   (24 points per true triangle, barycentric, so the match follows the cloth); per training frame the distance of
   the tracked vertex to its match, beside the reference surface moved by the skeleton alone (each vertex by its
   nearest body vertex's blended transform: what the nodes do without tracking), over the vertices within 2 cm of
   the true surface at the reference frame. How it fails: each frame's error split about the body's up axis through
   the true cloth's centroid (radial, outwards positive; tangential, anticlockwise about up; along up: signed means),
   the error of the lowest and highest quarter of the matched vertices (hem, waist), and the true cloth's hem radius
   (its lowest 15 %, about that axis) beside the tracked surface's. `--through` re-tracks the saved reference
   surface with the tracker's stop rule off (`garment_track.track(stop=False)`): the frames where the fit's tracker
   stopped, and how the surface goes wrong there.

    python -m benchmarks.garment_tracking PROJECT [--patches 32,64,128] [--flow] [--tracks] [--through]
        [--json OUT.json]
"""

from __future__ import annotations

import argparse
import json
from dataclasses import asdict, dataclass, replace
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
    frame_median_cm: tuple[float, ...] = ()  # [F] per training frame, over the nodes on the garment
    frame_p90_cm: tuple[float, ...] = ()
    node_mean_cm: tuple[float, ...] = ()  # [M] per node on the garment, over the frames


@dataclass(frozen=True)
class FlowError:
    pairs: int  # (view, consecutive training frame pair) images measured
    vertices: int  # garment vertex projections measured, over all pairs
    motion_px: float  # median true projected motion of those vertices between the two frames
    motion_p90_px: float
    error_px: float  # median end-point error of the optical flow there
    error_p90_px: float
    still_error_px: float  # median error of predicting no motion at all (= motion_px), for scale


@dataclass(frozen=True)
class TrackError:
    gap: int  # frames from the reference frame
    vertices: int  # garment vertex projections followed, over the views and both directions
    motion_px: float  # median true projected motion since the reference frame
    direct_px: float  # median end-point error of one flow from the reference frame straight to the frame
    direct_p90_px: float
    tracked: float  # fraction of the chained tracks still alive (forward-backward check, mask)
    chained_px: float  # median end-point error of the live chained tracks
    chained_p90_px: float


@dataclass(frozen=True)
class GaussianMotion:
    gaussians: int  # Gaussians within 2 cm of the garment, summed over the frames measured
    motion_px: float  # median projected motion of their garment vertices t -> t + 1
    motion_p90_px: float
    error_px: float  # median end-point error of the Gaussians' own projected motion
    error_p90_px: float


@dataclass(frozen=True)
class TrackingReport:
    frames: int
    garment_vertices: int
    nodes_on_garment: int  # nodes within 3 cm of the garment at the first training frame
    residuals: tuple[PatchResidual, ...]
    drift: tuple[NodeDrift, ...]
    nodes: tuple[int, ...] = ()  # the nodes on the garment (hull nodes are the last ones)
    flow: FlowError | None = None
    gaussian_motion: GaussianMotion | None = None  # Gaussian-field avatars only
    tracks: tuple[TrackError, ...] | None = None  # part 5 (--tracks)
    tracked_nodes: int = 0  # nodes the fit placed by its garment tracking on training frames (`track`)
    drawn: tuple[NodeDrift, ...] = ()  # part 2 over every garment vertex, in the frame of the node drawing it
    surface: "SurfaceError | None" = None  # part 6 (a fit with `track=true`)


@dataclass(frozen=True)
class SurfaceError:
    """Part 6: the tracked surface against the true cloth, per training frame (cm, mean over matched vertices)."""

    vertices: int  # tracked surface vertices within 2 cm of the true garment at the reference frame
    surface: int  # all tracked surface vertices
    frames_tracked: int
    tracked_cm: tuple[float, ...]  # [F] nan where the tracker lost the surface (the fit uses the skeleton there)
    skeleton_cm: tuple[float, ...]  # [F]
    parts: tuple["ErrorParts", ...] = ()  # [F] how the tracked surface errs (nan where not tracked)
    hem_radius_cm: tuple[float, ...] = ()  # [F] the true cloth's
    surface_hem_radius_cm: tuple[float, ...] = ()  # [F] the tracked surface's (nan where not tracked)
    through: bool = False  # re-tracked with the stop rule off (--through)


@dataclass(frozen=True)
class ErrorParts:
    """One frame's tracked-surface error about the body's up axis (part 6), cm."""

    radial: float  # signed mean, outwards positive
    tangential: float  # signed mean, anticlockwise about up
    along: float  # signed mean along up
    hem: float  # mean distance over the lowest quarter of the matched vertices
    waist: float  # the same, highest quarter


def error_parts(X: np.ndarray, Y: np.ndarray, up: np.ndarray) -> ErrorParts:
    """X [n, 3] tracked points against their true points Y [n, 3] (metres), `up` [3]: part 6's split of X - Y."""
    up = up / np.linalg.norm(up)
    e, rel = X - Y, Y - Y.mean(0)
    radial = rel - (rel @ up)[:, None] * up
    radial /= np.linalg.norm(radial, axis=1, keepdims=True).clip(min=1e-9)
    h = Y @ up
    lo, hi = np.percentile(h, [25, 75])
    dist = np.linalg.norm(e, axis=1)
    return ErrorParts(radial=float((e * radial).sum(1).mean() * 100),
                      tangential=float((e * np.cross(up, radial)).sum(1).mean() * 100),
                      along=float((e @ up).mean() * 100), hem=float(dist[h <= lo].mean() * 100),
                      waist=float(dist[h >= hi].mean() * 100))


def hem_radius(Y: np.ndarray, up: np.ndarray, share: float = 0.15) -> float:
    """Mean distance (cm) from the up axis through Y's centroid of the lowest `share` of the points Y [n, 3]."""
    up = up / np.linalg.norm(up)
    h = Y @ up
    low = Y[h <= np.quantile(h, share)]
    rel = low - Y.mean(0)
    return float(np.linalg.norm(rel - (rel @ up)[:, None] * up, axis=1).mean() * 100)


def _canonical(points: torch.Tensor, weights: torch.Tensor, joints: torch.Tensor) -> torch.Tensor:
    """points [F, P, 3] world, weights [P, J], joints [F, J, 4, 4] -> [F, P, 3] through the inverse blended
    transform."""
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
    """[M] indices of the nodes (centers [F, N, 3]) within `near` metres of the garment (garment [F, P, 3]) at
    frame 0."""
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


def drawn_drift(centers: torch.Tensor, linear: torch.Tensor, garment: torch.Tensor, means: torch.Tensor,
                opacity: torch.Tensor, per_node: int, min_opacity: float = 0.05) -> torch.Tensor:
    """Part 2's second measure: centers [F, N, 3] posed nodes, linear [F, N, 3, 3] their A_i, garment [F, P, 3],
    means [G, 3] and opacity [G] the posed Gaussians at frame 0 (node-major, `per_node` a node) -> the spread [P, F]
    (metres) of each garment vertex's offset in the frame of the node whose live Gaussian (opacity >= `min_opacity`)
    is nearest to it at frame 0: the node that draws it."""
    from scipy.spatial import cKDTree

    live = torch.nonzero(opacity >= min_opacity).reshape(-1)
    _, j = cKDTree(means[live].numpy()).query(garment[0].numpy())
    node = live[torch.as_tensor(j)] // per_node  # [P]
    off = (torch.linalg.inv(linear[:, node]) @ (garment - centers[:, node])[..., None])[..., 0]  # [F, P, 3]
    return (off - off.mean(0)).norm(dim=-1).T


def _facing_inside(capture, gt, view: str, frame: int, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The garment vertices of `frame` seen by `view`: -> (pixels [P, 2], keep [P] bool: the vertex faces the camera
    (the garment's faces turn away from the body: its outside) and projects inside the frame's mask)."""
    from avatarctl.geometry.triangulate import project

    cam = capture.cameras[view]
    x = gt.garment_vertices[gt.row(frame)].astype(np.float64)
    faces = gt.garment_faces
    p, _ = project(P, x)
    p = p[:, 0]
    n = np.zeros_like(x)
    fn = np.cross(x[faces[:, 1]] - x[faces[:, 0]], x[faces[:, 2]] - x[faces[:, 0]])
    for k in range(3):
        np.add.at(n, faces[:, k], fn)
    to_cam = cam.center[None] - x
    facing = (n * to_cam).sum(-1) > 0.3 * np.linalg.norm(n, axis=-1) * np.linalg.norm(to_cam, axis=-1)
    return p, facing & _in_mask(capture.mask(view, frame), p)


def _in_mask(mask: np.ndarray, p: np.ndarray) -> np.ndarray:
    """[n] bool: the pixels p [n, 2] (rounded) lie inside the image and its mask."""
    u, v = np.round(p[:, 0]).astype(int), np.round(p[:, 1]).astype(int)
    inside = (u >= 0) & (v >= 0) & (u < mask.shape[1]) & (v < mask.shape[0])
    inside[inside] &= mask[v[inside], u[inside]] > 0
    return inside


def _gray(capture, view: str, frame: int) -> np.ndarray:
    """The frame of one view as an 8-bit grey image (what the flow reads)."""
    import cv2

    return cv2.cvtColor(capture.image(view, frame), cv2.COLOR_RGB2GRAY)


def _farneback(ga: np.ndarray, gb: np.ndarray) -> np.ndarray:
    """OpenCV's Farneback flow [H, W, 2] (pixels) from grey image ga to gb (the parameters of part 3)."""
    import cv2

    return cv2.calcOpticalFlowFarneback(ga, gb, None, 0.5, 4, 15, 5, 5, 1.1, 0)


def _sample(flow: np.ndarray, p: np.ndarray) -> np.ndarray:
    """The flow [H, W, 2] read at pixels p [n, 2] (bilinear, border replicated) -> [n, 2]."""
    import cv2

    q = p.astype(np.float32)
    return np.stack([cv2.remap(flow[..., k], q[:, 0:1], q[:, 1:2], cv2.INTER_LINEAR,
                               borderMode=cv2.BORDER_REPLICATE)[:, 0] for k in range(2)], -1)


def flow_error(capture, gt, frames: list[int], views: list[str], max_pairs: int = 64) -> FlowError:
    """Part 3 of the module docstring over at most `max_pairs` (view, frame pair) images spread over the capture."""
    from avatarctl.geometry.triangulate import project, projection_matrices

    pairs = [(v, a, b) for v in views for a, b in zip(frames, frames[1:]) if b == a + 1]
    pairs = [pairs[i] for i in np.unique(np.linspace(0, len(pairs) - 1, min(max_pairs, len(pairs))).astype(int))]
    errors, motions = [], []
    for view, a, b in pairs:
        P = projection_matrices([capture.cameras[view]])
        pa, keep = _facing_inside(capture, gt, view, a, P)
        pb = project(P, gt.garment_vertices[gt.row(b)].astype(np.float64))[0][:, 0]
        if not keep.any():
            continue
        flow = _farneback(_gray(capture, view, a), _gray(capture, view, b))  # [H, W, 2] pixels, a -> b
        true = pb[keep] - pa[keep]
        errors.append(np.linalg.norm(_sample(flow, pa[keep]) - true, axis=-1))
        motions.append(np.linalg.norm(true, axis=-1))
    e, m = (np.concatenate(x) if x else np.zeros(0) for x in (errors, motions))
    med = (lambda x, q=50: float(np.percentile(x, q)) if len(x) else float("nan"))
    return FlowError(pairs=len(errors), vertices=int(len(e)), motion_px=med(m), motion_p90_px=med(m, 90),
                     error_px=med(e), error_p90_px=med(e, 90), still_error_px=med(m))


def long_range_tracks(capture, gt, frames: list[int], views: list[str], gaps: tuple[int, ...] = (1, 2, 3, 5, 8, 12, 20),
                      fb_px: float = 1.0) -> tuple[TrackError, ...]:
    """Part 5 of the module docstring: from the middle training frame r, the garment vertices each view sees there,
    followed to r -/+ gap by the flow chained over consecutive frames (a track ends where the forward-backward check
    of a step fails by more than `fb_px` pixels or it leaves the mask) and by one flow from r straight to r -/+ gap;
    the end-point error against the vertices' true projections there, beside their true motion since r."""
    from avatarctl.geometry.triangulate import project, projection_matrices

    have = set(frames)
    r = frames[len(frames) // 2]
    rows = {g: {"chained": [], "direct": [], "motion": []} for g in gaps}
    for view in views:
        P = projection_matrices([capture.cameras[view]])
        p0, keep = _facing_inside(capture, gt, view, r, P)
        start, g0 = p0[keep], _gray(capture, view, r)
        for step in (1, -1):
            p, alive, t, prev = start.copy(), np.ones(len(start), dtype=bool), r, g0
            for gap in range(1, max(gaps) + 1):
                if t + step not in have:
                    break
                g1 = _gray(capture, view, t + step)
                d = _sample(_farneback(prev, g1), p)
                alive &= np.linalg.norm(d + _sample(_farneback(g1, prev), p + d), axis=-1) < fb_px
                p, t, prev = p + d, t + step, g1
                alive &= _in_mask(capture.mask(view, t), p)
                if gap in rows:
                    true = project(P, gt.garment_vertices[gt.row(t)].astype(np.float64))[0][:, 0][keep]
                    row = rows[gap]
                    row["chained"].append(np.linalg.norm(p[alive] - true[alive], axis=-1))
                    row["direct"].append(np.linalg.norm(start + _sample(_farneback(g0, g1), start) - true, axis=-1))
                    row["motion"].append(np.linalg.norm(true - start, axis=-1))
    q = (lambda x, p: float(np.quantile(x, p)) if len(x) else float("nan"))
    out = []
    for g in gaps:
        if not sum(len(x) for x in rows[g]["direct"]):  # no vertex followed this far
            continue
        c, d, m = (np.concatenate(rows[g][k]) for k in ("chained", "direct", "motion"))
        out.append(TrackError(gap=g, vertices=len(d), motion_px=q(m, 0.5), direct_px=q(d, 0.5),
                              direct_p90_px=q(d, 0.9), tracked=len(c) / len(d), chained_px=q(c, 0.5),
                              chained_p90_px=q(c, 0.9)))
    return tuple(out)


def gaussian_motion(av, gt, frames: list[int], views: list[str], every: int = 5, near: float = 0.02,
                    min_opacity: float = 0.05) -> GaussianMotion:
    """Part 4 of the module docstring for a loaded Gaussian-field avatar `av`."""
    from scipy.spatial import cKDTree

    from avatarctl.geometry.triangulate import project, projection_matrices

    m = av.model
    have = set(frames)
    P = projection_matrices([av.capture.cameras[v] for v in views])
    errors, motions, count = [], [], 0
    for t in [f for f in frames if f + 1 in have][::every]:
        cond = av.conditioning(av.capture.motion.for_frames([t, t + 1]), frames_are_training=True)
        with torch.no_grad():
            posed = m.posed_gaussians(m.node_state(cond, mode="mean"))
        means = posed.means.double().numpy()
        ga, gb = (gt.garment_vertices[gt.row(f)].astype(np.float64) for f in (t, t + 1))
        dist, vert = cKDTree(ga).query(means[0])
        sel = (dist < near) & (posed.opacities[0] >= min_opacity).numpy()
        count += int(sel.sum())
        # [points, views, 2] pixels of the Gaussians at t, t + 1 and of their garment vertices at t, t + 1
        p0, p1, q0, q1 = (project(P, x)[0] for x in (means[0][sel], means[1][sel], ga[vert[sel]], gb[vert[sel]]))
        errors.append(np.linalg.norm((p1 - p0) - (q1 - q0), axis=-1).ravel())
        motions.append(np.linalg.norm(q1 - q0, axis=-1).ravel())
    e, mo = (np.concatenate(x) if x else np.zeros(0) for x in (errors, motions))
    q = (lambda x, p: float(np.quantile(x, p)) if len(x) else float("nan"))
    return GaussianMotion(gaussians=count, motion_px=q(mo, 0.5), motion_p90_px=q(mo, 0.9), error_px=q(e, 0.5),
                          error_p90_px=q(e, 0.9))


def measure(project_dir: str | Path, patch_counts: tuple[int, ...] = (32, 64, 128), flow: bool = False,
            tracks: bool = False, through: bool = False) -> TrackingReport:
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
    motion = av.capture.motion.for_frames(frames)
    cond = av.conditioning(motion, frames_are_training=True)
    posed = av.body.pose(motion)
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
    tracked = 0 if m.track_nodes is None else int(m.track_nodes.numel())
    saved = m.track_nodes
    with torch.no_grad():
        state = m.node_state(cond, mode="mean")  # with the fit's garment tracks, when it has them
        m.track_nodes = None
        bare = m.node_state(cond, mode="mean")  # the skeleton's frames: without them
        m.track_nodes = saved
    Tb = bare.transforms.double()
    skeleton = (Tb[..., :3, :3] @ m.node_rest.double()[None, :, :, None])[..., 0] + Tb[..., :3, 3]
    on = nodes_on_garment(state.centers.double(), garment)
    drift = [_drift("tracked" if tracked else "learned",
                    node_drift(state.centers.double(), state.transforms.double()[..., :3, :3], garment, on)),
             _drift("skeleton", node_drift(skeleton, Tb[..., :3, :3], garment, on))]
    drawn = ()
    if m.field_kind.splats:
        with torch.no_grad():
            posed = m.posed_gaussians(state)
        args = (garment, posed.means[0].double(), posed.opacities[0].double(), m.fields.per_node)
        drawn = tuple(replace(_drift(name, drawn_drift(c, A, *args)), node_mean_cm=())  # per frame, not per vertex
                      for name, c, A in (("tracked" if tracked else "learned", state.centers.double(),
                                          state.transforms.double()[..., :3, :3]),
                                         ("skeleton", skeleton, Tb[..., :3, :3])))
    track_file = project.paths.fit / "track" / "tracks.npz"
    return TrackingReport(frames=len(frames), garment_vertices=int(garment.shape[1]), nodes_on_garment=len(on),
                          nodes=tuple(on.tolist()), tracked_nodes=tracked, drawn=drawn,
                          surface=surface_error(av, gt, frames, track_file, through) if track_file.is_file()
                          else None,
                          residuals=tuple(residuals), drift=tuple(drift),
                          flow=flow_error(av.capture, gt, frames, list(av.capture.split.train_views)) if flow else None,
                          gaussian_motion=gaussian_motion(av, gt, frames, list(av.capture.split.train_views))
                          if m.field_kind.splats else None,
                          tracks=long_range_tracks(av.capture, gt, frames, list(av.capture.split.train_views))
                          if tracks else None)


def saved_settings(summary: Path) -> "TrackSettings":
    """The `TrackSettings` the fit's tracker ran with (fit/track/summary.json's "settings"); today's defaults when the
    summary does not hold them."""
    from avatarctl.fit.garment_track import TrackSettings

    saved = json.loads(summary.read_text()).get("settings", {}) if summary.is_file() else {}
    known = set(TrackSettings.__dataclass_fields__)
    return TrackSettings(**{k: tuple(v) if isinstance(v, list) else v for k, v in saved.items() if k in known})


def surface_error(av, gt, frames: list[int], path: Path, through: bool = False) -> SurfaceError:
    """Part 6 of the module docstring for the tracks in `path` (fit/garment_track.py's surface per frame);
    `through`: the saved reference surface tracked again with the stop rule off, with the fit's tracker settings."""
    from scipy.spatial import cKDTree

    from avatarctl.fit.garment_track import GarmentMesh, capture_input, skin_move, track

    d = np.load(path)
    assert [int(f) for f in d["frames"]] == frames, "the tracks are of other frames than the fit's"
    X, tracked = d["vertices"].astype(np.float64), d["tracked"]
    ref = int(d["reference"])  # frame index of the reference surface
    inp = capture_input(av.capture, av.body, av.template, frames, list(av.capture.split.train_views))
    if through:
        segments = int(d["segments"]) if "segments" in d else 0  # tracks of a fit before the twist pre-solve: none
        again = track(inp, GarmentMesh(X[ref], d["faces"].astype(np.int64), frames[ref], segments), ref,
                      saved_settings(path.parent / "summary.json"), stop=False)
        X, tracked = again.vertices, again.tracked
    faces = gt.garment_faces.astype(np.int64)
    bary = np.random.default_rng(0).dirichlet(np.ones(3), size=(len(faces), 24))  # [T, 24, 3]

    def points(f: int) -> np.ndarray:  # the true garment surface's points at frame f [T * 24, 3]
        return np.einsum("tkb,tbd->tkd", bary, gt.garment_vertices[gt.row(f)].astype(np.float64)[faces]).reshape(-1, 3)

    dist, match = cKDTree(points(frames[ref])).query(X[ref])
    near = dist < 0.02
    tr, sk, parts, hem, surface_hem = [], [], [], [], []
    nan = float("nan")
    for i, f in enumerate(frames):
        cloth = points(f)
        truth = cloth[match[near]]
        on = bool(tracked[i]) or i == ref
        tr.append(float(np.linalg.norm(X[i][near] - truth, axis=-1).mean() * 100) if on else nan)
        moved = skin_move(inp, X[ref][near], ref, i) if i != ref else X[ref][near]
        sk.append(float(np.linalg.norm(moved - truth, axis=-1).mean() * 100))
        parts.append(error_parts(X[i][near], truth, inp.up[i]) if on else ErrorParts(nan, nan, nan, nan, nan))
        hem.append(hem_radius(cloth, inp.up[i]))
        surface_hem.append(hem_radius(X[i], inp.up[i]) if on else nan)
    return SurfaceError(vertices=int(near.sum()), surface=len(X[ref]), frames_tracked=int(tracked.sum()),
                        tracked_cm=tuple(tr), skeleton_cm=tuple(sk), parts=tuple(parts), hem_radius_cm=tuple(hem),
                        surface_hem_radius_cm=tuple(surface_hem), through=through)


def _drift(motion: str, spread: torch.Tensor) -> NodeDrift:
    """spread [M, F] metres (`node_drift`) -> its summary in centimetres."""
    if not spread.numel():
        return NodeDrift(motion, float("nan"), float("nan"))
    cm = spread * 100
    return NodeDrift(motion, float(cm.mean()), float(cm.quantile(0.9)),
                     tuple(cm.median(0).values.tolist()), tuple(cm.quantile(0.9, dim=0).tolist()),
                     tuple(cm.mean(1).tolist()))


def main(argv: list[str] | None = None) -> TrackingReport:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("project")
    ap.add_argument("--patches", default="32,64,128", help="patch counts, comma list")
    ap.add_argument("--flow", action="store_true", help="also part 3: the optical flow against the garment's motion")
    ap.add_argument("--tracks", action="store_true", help="also part 5: long-range tracks (chained and direct flow)")
    ap.add_argument("--through", action="store_true",
                    help="part 6: track the fit's reference surface again with the stop rule off (minutes)")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    report = measure(args.project, tuple(int(x) for x in args.patches.split(",")), flow=args.flow, tracks=args.tracks,
                     through=args.through)
    print(f"{report.frames} training frames, {report.garment_vertices} garment vertices (CAPTURE/gt/geometry.npz)")
    print("residual of the garment's canonical motion after each patch's best per-frame motion, cm (mean / p90):")
    print(f"  {'skinning':<15} {'patches':>7}  {'translation':>15}  {'rigid':>15}")
    for r in report.residuals:
        print(f"  {r.skinning:<15} {r.patches:>7}  {r.translation_cm:6.2f} / {r.translation_p90_cm:6.2f}  "
              f"{r.rigid_cm:6.2f} / {r.rigid_p90_cm:6.2f}")
    if report.tracked_nodes:
        print(f"{report.tracked_nodes} nodes placed by the fit's garment tracking on training frames (track=true)")
    print(f"spread of the garment in the frames of the {report.nodes_on_garment} nodes on it, cm "
          f"(mean / p90; the 5 frames and nodes with the largest):")
    for d in report.drift:
        worst = np.argsort(d.frame_median_cm)[::-1][:5] if d.frame_median_cm else []
        nodes = np.argsort(d.node_mean_cm)[::-1][:5] if d.node_mean_cm else []
        print(f"  {d.motion:<9} {d.mean_cm:6.2f} / {d.p90_cm:6.2f}   frames "
              + ", ".join(f"{i} ({d.frame_median_cm[i]:.1f})" for i in worst) + "   nodes "
              + ", ".join(f"{report.nodes[i]} ({d.node_mean_cm[i]:.1f})" for i in nodes))
    if report.drawn:
        print("spread of every garment vertex in the frame of the node whose Gaussian draws it (the nearest live one "
              "at the first frame), cm (mean / p90):")
        for d in report.drawn:
            print(f"  {d.motion:<9} {d.mean_cm:6.2f} / {d.p90_cm:6.2f}")
    if report.flow is not None:
        f = report.flow
        print(f"optical flow (OpenCV Farneback) between consecutive training frames, {f.pairs} view pairs, "
              f"{f.vertices:,} visible garment vertices: true motion {f.motion_px:.2f} px (p90 {f.motion_p90_px:.2f}), "
              f"flow error {f.error_px:.2f} px (p90 {f.error_p90_px:.2f}); no motion at all would err "
              f"{f.still_error_px:.2f} px")
    if report.gaussian_motion is not None:
        g = report.gaussian_motion
        print(f"the {g.gaussians:,} Gaussians on the garment (every 5th training frame, each training view): projected "
              f"motion t -> t + 1 errs {g.error_px:.2f} px (p90 {g.error_p90_px:.2f}) against the garment's "
              f"{g.motion_px:.2f} px (p90 {g.motion_p90_px:.2f})")
    if report.tracks is not None:
        print("garment vertices followed from the middle training frame (px; median / p90):")
        print(f"  {'gap':>3} {'vertices':>8} {'motion':>7}  {'one flow':>13}  {'tracked':>7}  {'chained flow':>13}")
        for t in report.tracks:
            print(f"  {t.gap:>3} {t.vertices:>8,} {t.motion_px:7.2f}  {t.direct_px:6.2f} / {t.direct_p90_px:5.2f}  "
                  f"{100 * t.tracked:6.1f}%  {t.chained_px:6.2f} / {t.chained_p90_px:5.2f}")
    if report.surface is not None:
        e = report.surface
        tr, sk = np.asarray(e.tracked_cm), np.asarray(e.skeleton_cm)
        on = np.isfinite(tr)
        what = "the reference surface tracked again with the stop rule off" if e.through else "the fit's tracked"
        print(f"{what} garment surface ({e.vertices:,} of {e.surface:,} vertices within 2 cm of the true "
              f"cloth at the reference frame) against the true cloth, cm: {e.frames_tracked} of {len(tr)} frames "
              f"tracked, mean {np.mean(tr[on]):.2f} there against the skeleton's {np.mean(sk[on]):.2f}; the skeleton "
              f"over all frames {np.mean(sk):.2f}")
        print("  frame  tracked skeleton | radial tangential along | hem waist | hem radius: true surface")
        for i in range(0, len(tr), 4 if len(tr) > 24 else 1):
            p = e.parts[i]
            print(f"  {i:5d} {tr[i]:8.1f} {sk[i]:8.1f} | {p.radial:+6.1f} {p.tangential:+10.1f} {p.along:+5.1f} | "
                  f"{p.hem:4.1f} {p.waist:5.1f} | {e.hem_radius_cm[i]:15.1f} {e.surface_hem_radius_cm[i]:7.1f}")
    if args.json is not None:
        args.json.write_text(json.dumps(asdict(report), indent=1))
    return report


if __name__ == "__main__":
    main()
