"""Covariances of 3D Gaussians given by a rotation and scales, in groups that share a linear map (the nodes of the
structured local Gaussian fields: model/gaussian_field.py):

    Sigma_bnk = M M^T,   M = A_bn R(q_nk) diag(exp(s_nk))

`transformed_covariances` computes it in torch (differentiable: the twin) or, without gradients to keep, in one Warp
kernel (`_warp_kernels.transformed_covariances`): the same numbers up to float rounding, one launch for the ~45 small
torch operations that bound a single render on a GPU.
"""

from __future__ import annotations

import torch


def quaternion_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """[..., 4] quaternions (w, x, y, z), any norm -> [..., 3, 3] rotation matrices of the normalised quaternion."""
    q = q / q.norm(dim=-1, keepdim=True).clamp(min=1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], dim=-1).reshape(*q.shape[:-1], 3, 3)


def gram(M: torch.Tensor) -> torch.Tensor:
    """[..., 3, 3] -> M M^T from its 6 distinct row products (half the time of a batched matmul of 3x3 matrices on
    the CPU, forward and backward, measured at 100k matrices)."""
    r0, r1, r2 = M.unbind(-2)
    c00, c01, c02 = (r0 * r0).sum(-1), (r0 * r1).sum(-1), (r0 * r2).sum(-1)
    c11, c12, c22 = (r1 * r1).sum(-1), (r1 * r2).sum(-1), (r2 * r2).sum(-1)
    return torch.stack([c00, c01, c02, c01, c11, c12, c02, c12, c22], -1).reshape(M.shape)


def transformed_covariances(linear: torch.Tensor,  # [B, N, 3, 3] A: one linear map per group (node)
                            quats: torch.Tensor,  # [N, K, 4] (w, x, y, z), any norm
                            log_scales: torch.Tensor,  # [N, K, 3] log metres
                            ) -> torch.Tensor:  # [B, N, K, 3, 3]
    """Sigma = (A R S)(A R S)^T (module docstring): in torch where a gradient is to be kept, or the inputs are not
    float32; else in the Warp kernel (CPU or CUDA)."""
    B, N = linear.shape[:2]
    K = quats.shape[1]
    assert linear.shape == (B, N, 3, 3) and quats.shape == (N, K, 4) and log_scales.shape == (N, K, 3), \
        f"transformed_covariances: linear {list(linear.shape)}, quats {list(quats.shape)}, " \
        f"log_scales {list(log_scales.shape)}"
    grads = torch.is_grad_enabled() and any(t.requires_grad for t in (linear, quats, log_scales))
    if grads or any(t.dtype != torch.float32 for t in (linear, quats, log_scales)) or B * N * K == 0:
        L = quaternion_to_matrix(quats) * log_scales.exp()[:, :, None, :]  # [N, K, 3, 3] R S
        return gram(torch.einsum("bnij,nkjl->bnkil", linear, L))
    import warp as wp

    from avatarctl.splat.rasterizer import _kernels, torch_stream

    k = _kernels()
    dev = linear.device
    out = torch.empty(B, N, K, 3, 3, device=dev)
    inputs = [wp.from_torch(linear.detach().contiguous().reshape(B * N, 3, 3), dtype=wp.mat33),
              wp.from_torch(quats.detach().contiguous().reshape(N * K, 4), dtype=wp.vec4),
              wp.from_torch(log_scales.detach().contiguous().reshape(N * K, 3), dtype=wp.vec3), K, N,
              wp.from_torch(out.reshape(B * N * K, 3, 3), dtype=wp.mat33)]
    with torch_stream(dev):
        wp.launch(k.transformed_covariances, dim=B * N * K, inputs=inputs, device=str(dev))
    return out
