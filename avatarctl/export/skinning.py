"""An extracted canonical mesh as an animatable skinned avatar: skinning weights transferred from the body template
and the body model's joint transforms as a glTF joint hierarchy.

Skinning convention (`body/lbs.py`, Eq. 1-2): posed v = sum_j w_j M_j(theta) v_canonical, M_j: canonical -> world.
glTF 2.0 skins compute posed v = sum_j w_j G_j(theta) B_j^-1 v, with G_j the joint node's global matrix and B_j^-1
its inverse bind matrix. We bind every joint at its rest pivot c_j with identity rotation (B_j = translate(c_j)),
so G_j(theta) = M_j(theta) translate(c_j): the joint node sits at the posed pivot M_j c_j and carries M_j's
rotation; local (parent-relative) transforms are G_parent^-1 G_j, split into translation + rotation (+ the scale
left by a polar decomposition when M_j is not rigid, reported in `JointTrs.residual`). Any pivot gives exact
skinning; a good pivot makes the local translations nearly constant (bones of fixed length in other tools): the
export takes the joint centres of `body/joints.py` (the point M_j and its parent's M_p agree on over the frames).

The file's frame (`glb_frame`): a rigid change A = [C | -C o] from the capture's world: the rotation C [3, 3] takes
the capture's up to glTF's +Y, and the point o (world, metres) becomes the origin; the export puts o on the ground
under the body (`ground_origin`). It conjugates everything: v' = A v, M_j' = A M_j A^-1 (so the root motion is
relative to o).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

INFLUENCES = (4, 8)  # (joint, weight) pairs per vertex: glTF JOINTS_0 / WEIGHTS_0 (4, what every viewer reads),
#                      or also JOINTS_1 / WEIGHTS_1 (8; three.js reads only the first set)


@dataclass(frozen=True)
class SkinWeights:
    """Sparse skinning weights of the exported vertices (glTF JOINTS_n / WEIGHTS_n, 4 per set)."""

    joints: np.ndarray  # [verts, influences] uint16 joint indices, influences = 4 or 8; 0 where the weight is 0
    weights: np.ndarray  # [verts, influences] float32, rows sum to 1 (zeros pad)
    dense_residual: float  # max over vertices of the weight mass dropped by keeping the largest `influences`

    def dense(self, num_joints: int) -> np.ndarray:
        """[verts, J] dense float32 weights (what our LBS takes)."""
        out = np.zeros((self.joints.shape[0], num_joints), np.float32)
        rows = np.repeat(np.arange(self.joints.shape[0]), self.joints.shape[1])
        np.add.at(out, (rows, self.joints.astype(np.int64).ravel()), self.weights.ravel())  # padding adds 0
        return out


@dataclass(frozen=True)
class JointTrs:
    """Parent-relative joint transforms of a joint tree over frames (glTF node TRS / animation channels)."""

    translation: np.ndarray  # [frames, J, 3] metres
    rotation: np.ndarray  # [frames, J, 4] unit quaternions, glTF order (x, y, z, w), sign-continuous over frames
    scale: np.ndarray  # [frames, J, 3]
    residual: float  # max |TRS - local matrix| over frames and joints (0 for rigid transforms)


def transfer_weights(vertices: np.ndarray, template_vertices: np.ndarray, template_weights: np.ndarray,
                     k: int = 4) -> np.ndarray:
    """Dense weights [verts, J] for `vertices` [verts, 3] from the template's [V, 3] / [V, J]: inverse-distance
    blend of the `k` nearest template vertices (canonical space, metres); rows sum to 1."""
    from scipy.spatial import cKDTree

    k = min(k, template_vertices.shape[0])
    d, idx = cKDTree(np.asarray(template_vertices, np.float64)).query(np.asarray(vertices, np.float64), k=k)
    d, idx = d.reshape(len(vertices), k), idx.reshape(len(vertices), k)
    w = 1.0 / np.maximum(d, 1e-6)
    w /= w.sum(-1, keepdims=True)
    dense = (w[..., None] * np.asarray(template_weights, np.float64)[idx]).sum(1)
    return (dense / dense.sum(-1, keepdims=True)).astype(np.float32)


def sparsify(dense: np.ndarray, influences: int = 4) -> SkinWeights:
    """Keep the `influences` largest weights of each row [verts, J], renormalised."""
    V, J = dense.shape
    n = min(influences, J)
    idx = np.argsort(-dense, axis=1)[:, :n]
    w = np.take_along_axis(dense, idx, axis=1).astype(np.float64)
    kept = w.sum(-1)
    w = w / np.maximum(kept, 1e-12)[:, None]
    joints = np.zeros((V, influences), np.uint16)
    weights = np.zeros((V, influences), np.float32)
    joints[:, :n], weights[:, :n] = idx, w
    joints[weights == 0] = 0  # glTF: an unused influence has joint 0 (the validator warns otherwise)
    return SkinWeights(joints=joints, weights=weights, dense_residual=float(np.max(1.0 - kept)) if V else 0.0)


def _polar(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """[..., 3, 3] -> (R [..., 3, 3] proper rotation, S [..., 3, 3] symmetric) with A = R S."""
    U, s, Vt = np.linalg.svd(A)
    d = np.sign(np.linalg.det(U @ Vt))
    D = np.ones_like(s)
    D[..., -1] = d
    R = U @ (D[..., None] * Vt)
    S = np.swapaxes(Vt, -1, -2) @ ((D * s)[..., None] * Vt)
    return R, S


def matrix_to_quaternion(R: np.ndarray) -> np.ndarray:
    """[..., 3, 3] rotations -> [..., 4] unit quaternions (x, y, z, w), w >= 0 (Shepperd's method)."""
    R = np.asarray(R, np.float64)
    m00, m11, m22 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    cands = np.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)
    k = np.argmax(cands, axis=-1)
    s = np.sqrt(np.maximum(np.take_along_axis(cands, k[..., None], -1)[..., 0], 1e-30)) * 2  # 4 * |component|
    r = lambda a, b: R[..., a, b]  # noqa: E731
    w = np.where(k == 0, s / 4, np.where(k == 1, (r(2, 1) - r(1, 2)) / s, np.where(
        k == 2, (r(0, 2) - r(2, 0)) / s, (r(1, 0) - r(0, 1)) / s)))
    x = np.where(k == 0, (r(2, 1) - r(1, 2)) / s, np.where(k == 1, s / 4, np.where(
        k == 2, (r(0, 1) + r(1, 0)) / s, (r(0, 2) + r(2, 0)) / s)))
    y = np.where(k == 0, (r(0, 2) - r(2, 0)) / s, np.where(k == 1, (r(0, 1) + r(1, 0)) / s, np.where(
        k == 2, s / 4, (r(1, 2) + r(2, 1)) / s)))
    z = np.where(k == 0, (r(1, 0) - r(0, 1)) / s, np.where(k == 1, (r(0, 2) + r(2, 0)) / s, np.where(
        k == 2, (r(1, 2) + r(2, 1)) / s, s / 4)))
    q = np.stack([x, y, z, w], -1)
    q *= np.where(q[..., 3:] < 0, -1.0, 1.0)
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def quaternion_to_matrix(q: np.ndarray) -> np.ndarray:
    """[..., 4] (x, y, z, w) -> [..., 3, 3]."""
    q = np.asarray(q, np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = np.moveaxis(q, -1, 0)
    return np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
                     2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
                     2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1).reshape(q.shape[:-1]
                                                                                                  + (3, 3))


def glb_frame(basis: np.ndarray, origin: np.ndarray | None = None) -> np.ndarray:
    """[4, 4] A = [C | -C o]: world -> file frame, for a rotation `basis` C [3, 3] and the world point `origin` o [3]
    that becomes the file's origin (module docstring)."""
    A = np.eye(4)
    A[:3, :3] = basis
    if origin is not None:
        A[:3, 3] = -np.asarray(basis, np.float64) @ np.asarray(origin, np.float64)
    return A


def to_frame(points: np.ndarray, frame: np.ndarray) -> np.ndarray:
    """[..., 3] world points -> the file frame of `frame` (a [4, 4] `glb_frame` or a [3, 3] rotation)."""
    A = frame if frame.shape == (4, 4) else glb_frame(frame)
    return np.asarray(points, np.float64) @ A[:3, :3].T + A[:3, 3]


def conjugate(joint_transforms: np.ndarray, frame: np.ndarray) -> np.ndarray:
    """M' = A M A^-1 for [..., 4, 4] transforms and a rigid change of frame A ([4, 4] `glb_frame`, or a [3, 3]
    rotation C: M' = C M C^T)."""
    A = frame if frame.shape == (4, 4) else glb_frame(frame)
    A_inv = np.eye(4)
    A_inv[:3, :3] = A[:3, :3].T
    A_inv[:3, 3] = -A[:3, :3].T @ A[:3, 3]
    return A @ np.asarray(joint_transforms, np.float64) @ A_inv


def ground_origin(first: np.ndarray, lowest_up: float, basis: np.ndarray) -> np.ndarray:
    """The world point that becomes the file's origin: on the ground under the body. first [verts, 3]: the body's
    vertices at the first frame (world); lowest_up: the lowest height along the up axis (`basis` row 1, metres)
    that the feet reach over the motion. Horizontally the middle of the first frame's footprint (its bounding box
    in the ground plane), vertically the ground."""
    C = np.asarray(basis, np.float64)
    v = np.asarray(first, np.float64) @ C.T  # [verts, 3] in the file's axes
    mid = 0.5 * (v.min(0) + v.max(0))
    return C.T @ np.array([mid[0], float(lowest_up), mid[2]])


def joint_globals(joint_transforms: np.ndarray, pivots: np.ndarray) -> np.ndarray:
    """G_j = M_j translate(c_j): [frames, J, 4, 4], [J, 3] -> [frames, J, 4, 4] joint node global matrices."""
    T = np.tile(np.eye(4), (pivots.shape[0], 1, 1))
    T[:, :3, 3] = pivots
    return np.asarray(joint_transforms, np.float64) @ T[None]


def local_trs(globals_: np.ndarray, parents: tuple[int, ...]) -> JointTrs:
    """Parent-relative TRS of joint global matrices [frames, J, 4, 4] (roots: relative to the scene)."""
    G = np.asarray(globals_, np.float64)
    L = G.copy()
    for j, p in enumerate(parents):
        if p >= 0:
            L[:, j] = np.linalg.inv(G[:, p]) @ G[:, j]
    R, S = _polar(L[..., :3, :3])
    scale = np.diagonal(S, axis1=-2, axis2=-1).copy()
    q = matrix_to_quaternion(R)
    # sign continuity over frames (q and -q are the same rotation; linear / slerp interpolation needs the near one)
    for f in range(1, q.shape[0]):
        flip = (q[f] * q[f - 1]).sum(-1) < 0
        q[f, flip] *= -1
    rebuilt = quaternion_to_matrix(q) * scale[..., None, :]
    residual = float(np.abs(rebuilt - L[..., :3, :3]).max()) if L.size else 0.0
    return JointTrs(translation=L[..., :3, 3].astype(np.float32), rotation=q.astype(np.float32),
                    scale=scale.astype(np.float32), residual=residual)


def rest_trs(pivots: np.ndarray, parents: tuple[int, ...]) -> JointTrs:
    """The bind pose (M_j = identity): joint j at its pivot, identity rotation; one frame."""
    return local_trs(joint_globals(np.eye(4)[None, None].repeat(len(parents), 1), pivots), parents)


def up_to_y_basis(up: np.ndarray) -> np.ndarray:
    """[3, 3] rotation taking the unit world `up` to +Y (glTF's up), with the least rotation."""
    u = np.asarray(up, np.float64)
    u = u / np.linalg.norm(u)
    y = np.array([0.0, 1.0, 0.0])
    v, c = np.cross(u, y), float(u @ y)
    if c < -1 + 1e-9:
        return np.diag([1.0, -1.0, -1.0])
    K = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + K + K @ K / (1 + c)
