"""A loose skirt: its mesh, and an XPBD cloth simulation written as Warp CPU kernels.

The skirt is a `rings x segments` grid (a flared cone) whose top ring is attached to the body at the waist;
everything below hangs freely, swings with inertia and collides with the real deforming body mesh.

Solver (extended position-based dynamics, Macklin et al. 2016, in the small-steps form): per simulated frame,
`substeps` steps of dt = 1 / (fps * substeps); each step predicts x* = x + dt v + dt^2 g, then `iterations`
Gauss-Seidel sweeps over distance constraints (structural, shear and skip-one "bending" edges; each graph colour
is one kernel launch so no two threads touch one particle), then one collision pass against the body
mesh (`wp.Mesh.refit()` on the body interpolated to the substep time, `wp.mesh_query_point_no_sign` for the
closest point; a particle behind the surface, or closer than `thickness`, is moved to `thickness` outside);
then v = (x - x_prev) / dt with a little damping. Units: metres, seconds; world frame of anny (+z up).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from avatarctl.geometry.normals import vertex_normals
from avatarctl.synth.geometry import signed_volume


@dataclass(frozen=True)
class SkirtMesh:
    """The skirt's rest geometry around the reference-pose body."""

    rest: np.ndarray  # [P, 3] rest positions, metres
    faces: np.ndarray  # [F, 3] int32, normals pointing away from the body
    param: np.ndarray  # [P, 2] (angle around the body in radians [0, 2pi), height fraction 0 waist .. 1 hem)
    anchors: np.ndarray  # [segments] body vertex each waist-ring particle follows
    anchor_offset: float  # metres along the body vertex normal
    rings: int
    segments: int

    @property
    def num_particles(self) -> int:
        return self.rings * self.segments

    @property
    def waist(self) -> np.ndarray:
        """[segments] particle indices of the waist ring (pinned)."""
        return np.arange(self.segments)

    @property
    def hem(self) -> np.ndarray:
        """[segments] particle indices of the hem ring."""
        return np.arange(self.segments) + (self.rings - 1) * self.segments


def build_skirt(body_vertices: np.ndarray, body_faces: np.ndarray, torso: np.ndarray, rings: int, segments: int,
                length: float = 0.75, flare_deg: float = 24.0, anchor_offset: float = 0.008) -> SkirtMesh:
    """A flared skirt hanging from the narrowest part of the torso.

    body_vertices [V, 3] reference-pose body; body_faces [F, 3]; torso [V] bool, vertices allowed as anchors
    (trunk only, so that hands at waist height are never picked). `length` is measured along the cone.
    """
    V = np.asarray(body_vertices, dtype=np.float64)
    normals = vertex_normals(V, body_faces)
    tz = V[torso, 2]
    # waist: narrowest horizontal slice of the trunk between 10 and 22 cm above the pelvis
    best = None
    for z in np.arange(0.10, 0.22, 0.01):
        band = torso & (np.abs(V[:, 2] - z) < 0.015)
        if band.sum() < 12:
            continue
        width = np.ptp(V[band, 0])
        if best is None or width < best[0]:
            best = (width, z)
    if best is None:
        raise ValueError(f"no torso slice found between z=0.10 and 0.22 (torso z range {tz.min():.2f}..{tz.max():.2f})")
    z_w = best[1]
    band_idx = np.nonzero(torso & (np.abs(V[:, 2] - z_w) < 0.012))[0]
    centre = V[band_idx, :2].mean(0)
    rel = V[band_idx, :2] - centre
    ang = np.arctan2(rel[:, 1], rel[:, 0])
    rad = np.linalg.norm(rel, axis=1)
    theta = 2 * np.pi * np.arange(segments) / segments
    anchors = np.empty(segments, dtype=np.int64)
    for j, t in enumerate(theta):
        diff = np.abs((ang - t + np.pi) % (2 * np.pi) - np.pi)
        near = diff < (np.pi / segments) * 1.5
        cand = np.nonzero(near)[0] if near.any() else np.array([int(diff.argmin())])
        anchors[j] = band_idx[cand[rad[cand].argmax()]]
    top = V[anchors] + normals[anchors] * anchor_offset
    flare = math.radians(flare_deg)
    s = np.linspace(0.0, 1.0, rings)
    radial = np.stack([np.cos(theta), np.sin(theta), np.zeros(segments)], -1)  # [segments, 3]
    down = np.array([0.0, 0.0, -1.0])
    slant = radial * math.sin(flare) + down * math.cos(flare)  # [segments, 3]
    rest = top[None] + (s[:, None, None] * length) * slant[None]  # [rings, segments, 3]
    # grid triangles
    i, j = np.meshgrid(np.arange(rings - 1), np.arange(segments), indexing="ij")
    a = i * segments + j
    b = i * segments + (j + 1) % segments
    c = (i + 1) * segments + (j + 1) % segments
    d = (i + 1) * segments + j
    faces = np.concatenate([np.stack([a, d, c], -1).reshape(-1, 3), np.stack([a, c, b], -1).reshape(-1, 3)])
    P = rest.reshape(-1, 3)
    fn = np.cross(P[faces[:, 1]] - P[faces[:, 0]], P[faces[:, 2]] - P[faces[:, 0]])
    out = P[faces].mean(1) - np.array([centre[0], centre[1], 0.0])
    out[:, 2] = 0.0
    if np.einsum("ij,ij->i", fn, out).mean() < 0:
        faces = faces[:, ::-1]
    param = np.stack(np.broadcast_arrays(theta[None, :], s[:, None]), -1).reshape(-1, 2)
    return SkirtMesh(rest=P.astype(np.float32), faces=np.ascontiguousarray(faces, dtype=np.int32), param=param,
                     anchors=anchors, anchor_offset=anchor_offset, rings=rings, segments=segments)


def skirt_constraints(skirt: SkirtMesh) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Distance constraints of the grid: pairs [C, 2], kind [C] (0 stretch, 1 shear, 2 bend), rest length [C]."""
    R, S = skirt.rings, skirt.segments
    idx = np.arange(R * S).reshape(R, S)
    pairs, kinds = [], []

    def add(a: np.ndarray, b: np.ndarray, kind: int) -> None:
        pairs.append(np.stack([a.ravel(), b.ravel()], -1))
        kinds.append(np.full(a.size, kind))

    add(idx, np.roll(idx, -1, axis=1), 0)  # around
    add(idx[:-1], idx[1:], 0)  # down
    add(idx[:-1], np.roll(idx[1:], -1, axis=1), 1)  # shear /
    add(np.roll(idx[:-1], -1, axis=1), idx[1:], 1)  # shear \
    add(idx, np.roll(idx, -2, axis=1), 2)  # bend around
    add(idx[:-2], idx[2:], 2)  # bend down
    p = np.concatenate(pairs)
    k = np.concatenate(kinds)
    rest = np.linalg.norm(skirt.rest[p[:, 0]].astype(np.float64) - skirt.rest[p[:, 1]], axis=1)
    return p, k, rest


def color_constraints(pairs: np.ndarray, num_particles: int) -> tuple[np.ndarray, np.ndarray]:
    """Greedy graph colouring: no two constraints of one colour share a particle.

    Returns (order [C] permutation grouping constraints by colour, starts [colours + 1] offsets into it).
    """
    used: list[set[int]] = [set() for _ in range(num_particles)]
    color = np.empty(len(pairs), dtype=np.int64)
    for c, (a, b) in enumerate(pairs):
        k = 0
        taken = used[a] | used[b]
        while k in taken:
            k += 1
        color[c] = k
        used[a].add(k)
        used[b].add(k)
    order = np.argsort(color, kind="stable")
    counts = np.bincount(color)
    return order, np.concatenate([[0], np.cumsum(counts)])


@dataclass(frozen=True)
class ClothParams:
    """Material and solver settings of the skirt (SI units)."""

    substeps: int = 20
    iterations: int = 4
    gravity: float = -9.81  # m/s^2 along +z
    compliance_stretch: float = 1e-9  # m/N (XPBD alpha)
    compliance_shear: float = 1e-6
    compliance_bend: float = 1e-5
    damping: float = 0.6  # 1/s, velocity decay rate
    thickness: float = 0.007  # metres kept between the cloth and the body surface
    query_distance: float = 0.04  # metres searched for the closest body point


def _kernels():
    """Define the Warp kernels on first use (no compilation at import time)."""
    from avatarctl.device import init_warp

    wp = init_warp()

    @wp.kernel
    def predict(x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3), inv_m: wp.array(dtype=wp.float32),
                x_prev: wp.array(dtype=wp.vec3), g: wp.vec3, dt: float, keep: float):
        i = wp.tid()
        x_prev[i] = x[i]
        if inv_m[i] > 0.0:
            vi = v[i] * keep + g * dt
            v[i] = vi
            x[i] = x[i] + vi * dt

    @wp.kernel
    def pin(x: wp.array(dtype=wp.vec3), idx: wp.array(dtype=wp.int32), a: wp.array(dtype=wp.vec3),
            b: wp.array(dtype=wp.vec3), t: float):
        k = wp.tid()
        x[idx[k]] = a[k] * (1.0 - t) + b[k] * t

    @wp.kernel
    def lerp(a: wp.array(dtype=wp.vec3), b: wp.array(dtype=wp.vec3), t: float, out: wp.array(dtype=wp.vec3)):
        i = wp.tid()
        out[i] = a[i] * (1.0 - t) + b[i] * t

    @wp.kernel
    def solve_distance(x: wp.array(dtype=wp.vec3), inv_m: wp.array(dtype=wp.float32),
                       ca: wp.array(dtype=wp.int32), cb: wp.array(dtype=wp.int32),
                       rest: wp.array(dtype=wp.float32), alpha: wp.array(dtype=wp.float32),
                       lam: wp.array(dtype=wp.float32), offset: int, inv_dt2: float):
        k = wp.tid() + offset
        a = ca[k]
        b = cb[k]
        wa = inv_m[a]
        wb = inv_m[b]
        w = wa + wb
        if w > 0.0:
            d = x[a] - x[b]
            L = wp.length(d)
            if L > 1.0e-9:
                at = alpha[k] * inv_dt2
                dl = (-(L - rest[k]) - at * lam[k]) / (w + at)
                lam[k] = lam[k] + dl
                n = d / L
                x[a] = x[a] + n * (dl * wa)
                x[b] = x[b] - n * (dl * wb)

    @wp.kernel
    def collide(mesh: wp.uint64, x: wp.array(dtype=wp.vec3), inv_m: wp.array(dtype=wp.float32),
                thickness: float, max_dist: float):
        i = wp.tid()
        if inv_m[i] > 0.0:
            p = x[i]
            q = wp.mesh_query_point_no_sign(mesh, p, max_dist)
            if q.result:
                cp = wp.mesh_eval_position(mesh, q.face, q.u, q.v)
                n = wp.mesh_eval_face_normal(mesh, q.face)
                delta = p - cp
                s = wp.dot(delta, n)
                if s < 0.0:
                    x[i] = cp + n * thickness
                else:
                    dist = wp.length(delta)
                    if dist < thickness and dist > 1.0e-9:
                        x[i] = cp + delta * (thickness / dist)

    @wp.kernel
    def update_velocity(x: wp.array(dtype=wp.vec3), x_prev: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3),
                        inv_dt: float):
        i = wp.tid()
        v[i] = (x[i] - x_prev[i]) * inv_dt

    @wp.kernel
    def count_inside(mesh: wp.uint64, x: wp.array(dtype=wp.vec3), max_dist: float, tol: float,
                     out: wp.array(dtype=wp.int32)):
        i = wp.tid()
        q = wp.mesh_query_point_no_sign(mesh, x[i], max_dist)
        if q.result:
            cp = wp.mesh_eval_position(mesh, q.face, q.u, q.v)
            n = wp.mesh_eval_face_normal(mesh, q.face)
            if wp.dot(x[i] - cp, n) < -tol:
                wp.atomic_add(out, 0, 1)

    return dict(predict=predict, pin=pin, lerp=lerp, solve_distance=solve_distance, collide=collide,
                update_velocity=update_velocity, count_inside=count_inside)


_KERNELS: dict | None = None


def kernels() -> dict:
    global _KERNELS
    if _KERNELS is None:
        _KERNELS = _kernels()
    return _KERNELS


class SkirtSimulator:
    """Steps the skirt frame by frame against a moving body (Warp on the CPU)."""

    def __init__(self, skirt: SkirtMesh, body_vertices: np.ndarray, body_faces: np.ndarray, fps: float,
                 params: ClothParams = ClothParams(), collide_vertices: np.ndarray | None = None):
        """body_vertices [V, 3] the body at the first simulated frame; body_faces [F, 3]; collide_vertices [V]
        bool, the body parts the skirt can reach (faces touching them form the collision mesh; default all)."""
        import warp as wp

        self.wp = wp
        self.k = kernels()
        self.skirt = skirt
        self.params = params
        self.fps = fps
        self.dt = 1.0 / (fps * params.substeps)
        faces = np.asarray(body_faces, dtype=np.int32)
        if signed_volume(np.asarray(body_vertices), faces) < 0:  # collision normals must point out of the body
            faces = faces[:, ::-1]
        self.body_faces = np.ascontiguousarray(faces)
        keep = np.ones(len(faces), bool) if collide_vertices is None else collide_vertices[faces].any(1)
        self.collision_faces = np.ascontiguousarray(faces[keep])
        # faces around each waist anchor, for its normal
        touching = np.isin(faces, skirt.anchors).any(1)
        self._anchor_faces = faces[touching]
        dev = "cpu"
        P = skirt.num_particles
        inv_m = np.ones(P, dtype=np.float32)
        inv_m[skirt.waist] = 0.0
        pairs, kinds, rest = skirt_constraints(skirt)
        order, self.color_starts = color_constraints(pairs, P)
        pairs, kinds, rest = pairs[order], kinds[order], rest[order]
        alpha = np.array([params.compliance_stretch, params.compliance_shear, params.compliance_bend],
                         dtype=np.float32)[kinds]
        self.x = wp.array(skirt.rest, dtype=wp.vec3, device=dev)
        self.x_prev = wp.zeros(P, dtype=wp.vec3, device=dev)
        self.v = wp.zeros(P, dtype=wp.vec3, device=dev)
        self.inv_m = wp.array(inv_m, dtype=wp.float32, device=dev)
        self.ca = wp.array(pairs[:, 0].astype(np.int32), dtype=wp.int32, device=dev)
        self.cb = wp.array(pairs[:, 1].astype(np.int32), dtype=wp.int32, device=dev)
        self.rest = wp.array(rest.astype(np.float32), dtype=wp.float32, device=dev)
        self.alpha = wp.array(alpha, dtype=wp.float32, device=dev)
        self.lam = wp.zeros(len(pairs), dtype=wp.float32, device=dev)
        self.pin_idx = wp.array(skirt.waist.astype(np.int32), dtype=wp.int32, device=dev)
        bv = np.asarray(body_vertices, dtype=np.float32)
        self.body_a = wp.array(bv, dtype=wp.vec3, device=dev)
        self.body_b = wp.array(bv, dtype=wp.vec3, device=dev)
        self.body_pts = wp.array(bv, dtype=wp.vec3, device=dev)
        self.mesh = wp.Mesh(points=self.body_pts, indices=wp.array(self.collision_faces.ravel(), dtype=wp.int32,
                                                                      device=dev))
        self.pins_a = wp.array(self.anchor_targets(bv), dtype=wp.vec3, device=dev)
        self.pins_b = wp.array(self.anchor_targets(bv), dtype=wp.vec3, device=dev)
        self.dev = dev
        self._record_launches()

    def _record_launches(self) -> None:
        """Pre-packed kernel launches (a recorded `wp.Launch` costs ~6 us instead of ~70 us per call)."""
        wp, k, p, dev = self.wp, self.k, self.params, self.dev
        P, S = self.skirt.num_particles, self.skirt.segments
        nV = self.body_pts.shape[0]
        keep = math.exp(-p.damping * self.dt)
        g = wp.vec3(0.0, 0.0, p.gravity)

        def rec(kernel, dim, inputs):
            return wp.launch(kernel, dim=dim, inputs=inputs, device=dev, record_cmd=True)

        self._predict = rec(k["predict"], P, [self.x, self.v, self.inv_m, self.x_prev, g, self.dt, keep])
        ts = [(s + 1) / p.substeps for s in range(p.substeps)]
        self._pin_cmds = [rec(k["pin"], S, [self.x, self.pin_idx, self.pins_a, self.pins_b, t]) for t in ts]
        self._lerp_cmds = [rec(k["lerp"], nV, [self.body_a, self.body_b, t, self.body_pts]) for t in ts]
        starts = self.color_starts
        self._solve_cmds = [rec(k["solve_distance"], int(starts[c + 1] - starts[c]),
                                [self.x, self.inv_m, self.ca, self.cb, self.rest, self.alpha, self.lam,
                                 int(starts[c]), 1.0 / (self.dt * self.dt)]) for c in range(len(starts) - 1)]
        self._collide = rec(k["collide"], P, [self.mesh.id, self.x, self.inv_m, p.thickness, p.query_distance])
        self._update_velocity = rec(k["update_velocity"], P, [self.x, self.x_prev, self.v, 1.0 / self.dt])

    def anchor_targets(self, body_vertices: np.ndarray) -> np.ndarray:
        """[segments, 3] waist-ring positions for a body pose: anchor vertex + offset along its normal."""
        n = vertex_normals(np.asarray(body_vertices, dtype=np.float64), self._anchor_faces)
        a = self.skirt.anchors
        return (body_vertices[a] + n[a] * self.skirt.anchor_offset).astype(np.float32)

    def step(self, body_next: np.ndarray) -> np.ndarray:
        """Advance one frame (1 / fps) while the body moves to `body_next` [V, 3]; returns particles [P, 3]."""
        wp = self.wp
        # the previous frame's body becomes the start of this frame's interpolation
        wp.copy(self.body_a, self.body_b)
        wp.copy(self.pins_a, self.pins_b)
        bn = np.asarray(body_next, dtype=np.float32)
        self.body_b.assign(bn)
        self.pins_b.assign(self.anchor_targets(bn))
        p = self.params
        for s in range(p.substeps):
            self._predict.launch()
            self._pin_cmds[s].launch()
            self._lerp_cmds[s].launch()
            self.mesh.refit()
            self.lam.zero_()
            for _ in range(p.iterations):
                for cmd in self._solve_cmds:
                    cmd.launch()
            self._collide.launch()
            self._update_velocity.launch()
        return self.x.numpy().copy()

    def count_penetrations(self, tol: float = 0.002) -> int:
        """Particles more than `tol` metres behind the body surface at the current state."""
        out = self.wp.zeros(1, dtype=self.wp.int32, device=self.dev)
        self.wp.launch(self.k["count_inside"], dim=self.skirt.num_particles,
                       inputs=[self.mesh.id, self.x, self.params.query_distance, tol, out], device=self.dev)
        return int(out.numpy()[0])
