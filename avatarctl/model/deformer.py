"""The node deformer: where the structured local radiance fields sit and how they move (paper Sec. 3, 4.1).

Pure functions, batched and differentiable; the model (`avatar.py`) only wires them together.

Frames and units: canonical space = the body template's rest pose, posed space = world of the capture, metres.
`joint_transforms` are the body model's M_j(theta): canonical -> world (Eq. 1). Shapes use the vocabulary
`frames` (the batch B of conditioned frames), `nodes` (N), `joints` (J), `points` (samples in the posed space).
"""

from __future__ import annotations

import math
from collections import deque

import torch

from avatarctl.body.lbs import blend_transforms, transform_points


# ---- node placement ---------------------------------------------------------------------------------------------
def farthest_point_sampling(points: torch.Tensor, n: int, seed: int = 0,
                            existing: torch.Tensor | None = None) -> torch.Tensor:
    """Indices [n] of `n` points of `points` [V, 3] chosen by farthest point sampling (Euclidean).

    The first index is drawn from a generator seeded with `seed` (deterministic on every device); each next point
    is the one farthest from all chosen so far (ties: the lowest index), so the nodes cover the surface evenly.
    With `existing` [M, 3] points already chosen (e.g. the surface nodes, for fit/hull_nodes.py), the distances
    start from them and the first pick is the point farthest from them (`seed` unused).
    """
    V = points.shape[0]
    if not 0 < n <= V:
        raise ValueError(f"farthest_point_sampling: need 0 < n <= {V} points, got n={n}")
    pts = points.detach().to(torch.float64)
    idx = torch.empty(n, dtype=torch.long)
    if existing is None:
        g = torch.Generator().manual_seed(int(seed))
        first = int(torch.randint(V, (1,), generator=g))
        idx[0] = first
        dist = ((pts - pts[first]) ** 2).sum(-1)  # [V] squared distance to the chosen set
        start = 1
    else:
        dist = torch.cdist(pts, existing.detach().to(pts)).min(1).values ** 2
        start = 0
    for k in range(start, n):
        nxt = int(torch.argmax(dist))
        idx[k] = nxt
        dist = torch.minimum(dist, ((pts - pts[nxt]) ** 2).sum(-1))
    return idx.to(points.device)


# ---- pose condition (Eq. 8) --------------------------------------------------------------------------------------
def kinematic_hop_distance(parents: tuple[int, ...] | list[int]) -> torch.Tensor:
    """[J, J] long: number of bones on the path between two joints of the kinematic tree (0 on the diagonal)."""
    J = len(parents)
    adj: list[list[int]] = [[] for _ in range(J)]
    for j, p in enumerate(parents):
        if p >= 0:
            adj[j].append(p)
            adj[p].append(j)
    hops = torch.full((J, J), -1, dtype=torch.long)
    for s in range(J):
        hops[s, s] = 0
        queue = deque([s])
        while queue:
            a = queue.popleft()
            for b in adj[a]:
                if hops[s, b] < 0:
                    hops[s, b] = hops[s, a] + 1
                    queue.append(b)
    if (hops < 0).any():
        raise ValueError("kinematic_hop_distance: the joint tree is not connected (more than one root)")
    return hops


def pose_attention_map(parents: tuple[int, ...] | list[int], hops: int) -> torch.Tensor:
    """The SCANimate-style attention map W [J, J] of Eq. 8: W[k, j] = 1 if joints k and j are at most `hops`
    bones apart in the kinematic tree, else 0. Symmetric, binary, ones on the diagonal.

    With it, (W @ omega_i)[k] = sum of node i's skinning weights on the joints near joint k: a node attends to the
    rotations of the joints that move it and their neighbours, and ignores the rest of the body.
    """
    return (kinematic_hop_distance(parents) <= hops).to(torch.float32)


def node_pose_attention(skin_weights: torch.Tensor, attention_map: torch.Tensor) -> torch.Tensor:
    """(W . omega_i) of Eq. 8 for every node: [N, J] skinning weights, [J, J] W -> [N, J] attention in [0, 1]."""
    return (skin_weights @ attention_map.T.to(skin_weights.dtype)).clamp(max=1.0)


def node_pose_condition(pose_features: torch.Tensor, attention: torch.Tensor) -> torch.Tensor:
    """Eq. 8: theta_i = (W . omega_i) o theta, per node and frame.

    Args:
        pose_features: [frames, J, 3] local joint rotations theta (axis-angle, radians, root zeroed).
        attention: [N, J] (W . omega_i) from `node_pose_attention`.
    Returns:
        [frames, N, 3J] the pose condition of every node (each joint's 3 values scaled by its attention).
    """
    B, J, _ = pose_features.shape
    assert attention.shape[-1] == J, f"attention {tuple(attention.shape)} vs pose_features {tuple(pose_features.shape)}"
    cond = attention[None, :, :, None] * pose_features[:, None, :, :]  # [frames, N, J, 3]
    return cond.reshape(B, attention.shape[0], 3 * J)


# ---- Eq. 1-4: node transforms, posed nodes, local coordinates ---------------------------------------------------
def node_transforms(node_skin_weights: torch.Tensor, joint_transforms: torch.Tensor) -> torch.Tensor:
    """Eq. 1: T_i = sum_j omega_ij M_j(theta). [N, J], [frames, J, 4, 4] -> [frames, N, 4, 4] (not rigid in general)."""
    return blend_transforms(node_skin_weights, joint_transforms)


def posed_node_centers(transforms: torch.Tensor, rest_centers: torch.Tensor, delta_n: torch.Tensor) -> torch.Tensor:
    """Eq. 3 (Eq. 2 when delta_n = 0): n_i = T_i (n_bar_i + Delta n_i).

    transforms [frames, N, 4, 4], rest_centers [N, 3] canonical, delta_n [frames, N, 3] canonical -> [frames, N, 3].
    """
    return transform_points(transforms, rest_centers[None] + delta_n)


def local_coordinates(points: torch.Tensor, transforms: torch.Tensor, rest_centers: torch.Tensor,
                      delta_n: torch.Tensor) -> torch.Tensor:
    """Eq. 4 literally: p_i = T_i^-1 p - (n_bar_i + Delta n_i). Broadcasting [..., 3], [..., 4, 4], [..., 3]."""
    return transform_points(torch.linalg.inv(transforms), points) - (rest_centers + delta_n)


def local_coordinates_centered(points: torch.Tensor, linear_inv: torch.Tensor, centers: torch.Tensor) -> torch.Tensor:
    """Eq. 4 in the form the model evaluates: p_i = A_i^-1 (p - n_i), with A_i the 3x3 linear part of T_i and n_i the
    posed node (Eq. 3). Equal to `local_coordinates` because T_i^-1 p - T_i^-1 n_i = A_i^-1 (p - n_i); it avoids
    subtracting two large numbers. points [..., 3], linear_inv [..., 3, 3], centers [..., 3] -> [..., 3]."""
    return (linear_inv @ (points - centers)[..., None]).squeeze(-1)


# ---- Eq. 6: blending weights -------------------------------------------------------------------------------------
def support_radius(sigma: float, eps: float) -> float:
    """Distance (metres) at which Eq. 6 reaches zero: exp(-r^2 / 2 sigma^2) = eps  <=>  r = sigma sqrt(-2 ln eps)."""
    return sigma * math.sqrt(-2.0 * math.log(eps))


def blending_weights(sq_dist: torch.Tensor, sigma: float, eps: float) -> torch.Tensor:
    """Eq. 6: w_i = max(exp(-||p - n_i||^2 / 2 sigma^2) - eps, 0), from squared distances [...] (metres^2)."""
    return torch.clamp(torch.exp(-sq_dist / (2.0 * sigma * sigma)) - eps, min=0.0)


# ---- neighbour search and ray bounds -----------------------------------------------------------------------------
def candidate_pairs(points: torch.Tensor, point_frame: torch.Tensor, centers: torch.Tensor,
                    radius: float) -> tuple[torch.Tensor, torch.Tensor]:
    """All (point, node) pairs closer than `radius` (plus a 1e-4 relative margin), without gradients.

    points [P, 3] posed, point_frame [P] long (index into the frames of `centers`), centers [frames, N, 3].
    Returns (point_idx [pairs], node_idx [pairs]), long. Callers evaluate Eq. 6 exactly on these pairs and drop
    the ones whose weight is 0, so the margin only guards against rounding in the distance computation.
    """
    r2 = (radius * (1.0 + 1e-4) + 1e-6) ** 2
    pi, ni = [], []
    with torch.no_grad():
        for b in range(centers.shape[0]):
            sel = (point_frame == b).nonzero(as_tuple=True)[0]
            if sel.numel() == 0:
                continue
            d2 = torch.cdist(points[sel].float(), centers[b].float()) ** 2  # [P_b, N]
            p, n = (d2 < r2).nonzero(as_tuple=True)
            pi.append(sel[p])
            ni.append(n)
    if not pi:
        empty = torch.zeros(0, dtype=torch.long, device=points.device)
        return empty, empty
    return torch.cat(pi), torch.cat(ni)


def ray_sphere_bounds(origins: torch.Tensor, dirs: torch.Tensor, centers: torch.Tensor,
                      radius: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Entry/exit of each ray through the union of the node-influence spheres of its frame.

    origins, dirs [rays, 3] (dirs unit, world), centers [rays, N, 3] (the nodes of each ray's frame), radius metres.
    Returns near [rays], far [rays] (distances along the ray, near >= 0) and hit [rays] bool. near/far of missed
    rays are 0. Between near and far the ray may cross gaps between spheres; those samples get zero density.
    """
    oc = centers - origins[:, None, :]  # [rays, N, 3]
    tc = (oc * dirs[:, None, :]).sum(-1)  # [rays, N] distance to the closest approach
    perp2 = (oc * oc).sum(-1) - tc * tc
    h2 = radius * radius - perp2
    hit_node = (h2 > 0) & (tc + torch.sqrt(h2.clamp_min(0)) > 0)
    half = torch.sqrt(h2.clamp_min(0))
    inf = torch.finfo(centers.dtype).max
    t0 = torch.where(hit_node, (tc - half).clamp_min(0), torch.full_like(tc, inf))
    t1 = torch.where(hit_node, tc + half, torch.zeros_like(tc))
    hit = hit_node.any(-1)
    near = torch.where(hit, t0.min(-1).values, torch.zeros_like(hit, dtype=centers.dtype))
    far = torch.where(hit, t1.max(-1).values, torch.zeros_like(near))
    return near.detach(), far.detach(), hit
