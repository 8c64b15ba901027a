"""The posed Gaussians of one frame as a 3D Gaussian splatting `.ply` (the Inria layout every splat viewer reads:
SuperSplat, viser, three.js splat loaders, nerfstudio).

One `vertex` element, binary little-endian float32 properties
    x y z nx ny nz f_dc_0 f_dc_1 f_dc_2 f_rest_0 ... f_rest_44 opacity scale_0 scale_1 scale_2 rot_0 rot_1 rot_2 rot_3
with opacity a logit, scales log metres, rotation a unit quaternion (w, x, y, z), colour = 0.5 + 0.28209479 f_dc, and
`f_rest` channel-major (red's 15 coefficients, then green's, then blue's) for SH degree 3; with `sh_degree` 1 our
degree-1 bands fill the first 3 of each channel, the rest are 0 (all 0 with the default degree 0: view-independent
colour). Normals are 0 (unused by splat viewers). The header's comment `avatarctl low_pass <px^2>` names the
screen-space low-pass the avatar was trained with (`model.gaussians.low_pass`; 3DGS viewers add their own, 0.3).

World frame: the capture's (metres), as the posed meshes' PLY. The model keeps its SH in each node's local frame (the
view dependence turns with the body, model/gaussian_field.py); here the degree-1 band is turned into the world frame
by the rotation closest to the node's A_i (polar decomposition), and each Gaussian's world covariance
A_i R S^2 R^T A_i^T is split again into a rotation and scales (eigen-decomposition).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from avatarctl.atomic import atomic_path

REST_PER_CHANNEL = 15  # SH degree 3 has 16 coefficients per channel: 1 DC + 15 in f_rest


def _matrix_to_quaternion(R: np.ndarray) -> np.ndarray:
    """[G, 3, 3] rotations -> [G, 4] unit quaternions (w, x, y, z), w >= 0."""
    from scipy.spatial.transform import Rotation

    xyzw = Rotation.from_matrix(R).as_quat()
    q = np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=1)
    return q * np.where(q[:, :1] < 0, -1.0, 1.0)


def splat_arrays(means: torch.Tensor, covars: torch.Tensor, sh: torch.Tensor, opacities: torch.Tensor,
                 linear: torch.Tensor, per_node: int) -> dict[str, np.ndarray]:
    """The `.ply` columns of G posed Gaussians of one frame: means [G, 3], covars [G, 3, 3], sh [G, S, 3] (local
    frame, S = 1 or 4), opacities [G], linear [N, 3, 3] the nodes' A_i (G = N per_node, node-major)."""
    G = means.shape[0]
    cov = covars.detach().double().cpu()
    evals, evecs = torch.linalg.eigh(cov)  # ascending; columns are axes
    evecs = torch.where(torch.linalg.det(evecs)[:, None, None] < 0, evecs * torch.tensor([-1.0, 1, 1]), evecs)
    out = {"xyz": means.detach().float().cpu().numpy(),
           "f_dc": sh[:, 0].detach().float().cpu().numpy(),
           "opacity": torch.logit(opacities.detach().double().cpu().clamp(1e-6, 1 - 1e-6)).float().numpy(),
           "scale": 0.5 * torch.log(evals.clamp(min=1e-14)).float().numpy(),
           "rot": _matrix_to_quaternion(evecs.numpy()).astype(np.float32)}
    rest = np.zeros((G, 3, REST_PER_CHANNEL), dtype=np.float32)
    if sh.shape[1] > 1:
        U, _, Vh = torch.linalg.svd(linear.detach().double().cpu())
        rot = (U @ Vh).repeat_interleave(per_node, dim=0)  # [G, 3, 3] nearest rotation to A_i
        b = sh[:, 1:4].detach().double().cpu()  # [G, 3 bands, 3 channels]; colour += C1 d . v, v = (-b3, -b1, b2)
        v = torch.stack([-b[:, 2], -b[:, 0], b[:, 1]], dim=1)  # [G, 3 xyz, 3 channels] in the local frame
        w = rot @ v  # world
        world = torch.stack([-w[:, 1], w[:, 2], -w[:, 0]], dim=1)  # back to the bands, [G, 3 bands, 3 channels]
        rest[:, :, :3] = world.permute(0, 2, 1).float().numpy()
    out["f_rest"] = rest.reshape(G, 3 * REST_PER_CHANNEL)
    return out


def write_splat_ply(dest: str | Path, cols: dict[str, np.ndarray], low_pass: float) -> Path:
    """Write `splat_arrays` columns as a binary 3DGS `.ply`, atomically; `low_pass` (px^2) goes in a header comment."""
    G = cols["xyz"].shape[0]
    names = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
             + [f"f_rest_{i}" for i in range(3 * REST_PER_CHANNEL)]
             + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])
    data = np.concatenate([cols["xyz"], np.zeros((G, 3), np.float32), cols["f_dc"], cols["f_rest"],
                           cols["opacity"][:, None], cols["scale"], cols["rot"]], axis=1).astype("<f4")
    assert data.shape == (G, len(names)), f"{data.shape} vs {len(names)} properties"
    header = "ply\nformat binary_little_endian 1.0\n" + f"comment avatarctl low_pass {float(low_pass)!r}\n" \
        + f"element vertex {G}\n" \
        + "".join(f"property float {n}\n" for n in names) + "end_header\n"
    with atomic_path(dest) as tmp:
        with tmp.open("wb") as f:
            f.write(header.encode("ascii"))
            f.write(np.ascontiguousarray(data).tobytes())
    return Path(dest)
