"""Rays cast against a triangle mesh with Warp's BVH (`wp.Mesh`, `wp.mesh_query_ray`): the synth's renderer, the mesh
export's rasterizer and its level choice, which cameras see which points (`seen_by`: the garment tracker, the
cross-camera colour estimate)."""

from __future__ import annotations

import numpy as np


def _cast_kernel():
    from avatarctl.device import init_warp

    wp = init_warp()

    @wp.kernel
    def cast(mesh: wp.uint64, origin: wp.vec3, dirs: wp.array(dtype=wp.vec3), max_t: float,
             face: wp.array(dtype=wp.int32), t_hit: wp.array(dtype=wp.float32)):
        i = wp.tid()
        q = wp.mesh_query_ray(mesh, origin, dirs[i], max_t)
        if q.result:
            face[i] = q.face
            t_hit[i] = q.t
        else:
            face[i] = -1
            t_hit[i] = 0.0

    return cast


_CAST = None


class RayCaster:
    """A triangle mesh (fixed topology, moving vertices) that rays are cast against."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        """vertices [V, 3] metres; faces [F, 3] int."""
        global _CAST
        import warp as wp

        if _CAST is None:
            _CAST = _cast_kernel()
        self.wp = wp
        self.points = wp.array(np.asarray(vertices, dtype=np.float32), dtype=wp.vec3, device="cpu")
        self.mesh = wp.Mesh(points=self.points, indices=wp.array(np.asarray(faces, dtype=np.int32).ravel(),
                                                                  dtype=wp.int32, device="cpu"))

    def update(self, vertices: np.ndarray) -> None:
        """Move the vertices [V, 3] and refit the BVH."""
        self.points.assign(np.asarray(vertices, dtype=np.float32))
        self.mesh.refit()

    def cast(self, origin: np.ndarray, dirs: np.ndarray, max_t: float = 100.0) -> tuple[np.ndarray, np.ndarray]:
        """origin [3], dirs [N, 3] unit -> (face [N] int32, -1 = miss; t [N] float32 metres along the ray)."""
        wp = self.wp
        n = dirs.shape[0]
        d = wp.array(np.ascontiguousarray(dirs, dtype=np.float32), dtype=wp.vec3, device="cpu")
        face = wp.empty(n, dtype=wp.int32, device="cpu")
        t = wp.empty(n, dtype=wp.float32, device="cpu")
        wp.launch(_CAST, dim=n, inputs=[self.mesh.id, wp.vec3(*np.asarray(origin, dtype=np.float32)), d, max_t,
                                        face, t], device="cpu")
        return face.numpy(), t.numpy()


def seen_by(caster: RayCaster, centers: np.ndarray, points: np.ndarray, normals: np.ndarray, min_cos: float,
            two_sided: bool = False, tolerance: float = 0.01) -> np.ndarray:
    """[C, N] bool: camera c (centre `centers` [C, 3]) sees point `points` [N, 3] (on the caster's mesh): the ray from
    the camera hits the mesh no nearer than `tolerance` metres before the point, and the point's unit normal
    `normals` [N, 3] faces the camera by cos >= `min_cos` (either side when `two_sided`: a surface whose normals
    are not oriented)."""
    out = np.zeros((len(centers), len(points)), dtype=bool)
    for c, o in enumerate(np.asarray(centers, dtype=np.float64)):
        d = points - o
        dist = np.linalg.norm(d, axis=-1)
        d = d / np.maximum(dist, 1e-12)[:, None]
        face, t = caster.cast(o, d)
        cos = -(normals * d).sum(-1)
        out[c] = (face >= 0) & (t > dist - tolerance) & ((np.abs(cos) if two_sided else cos) >= min_cos)
    return out
