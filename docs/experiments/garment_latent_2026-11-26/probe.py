"""Issue 18, hypotheses 1 and 5, measured on a trained project: is the cVAE latent z used, is e used?

Not part of the package.

    python probe.py PROJECT [CAPTURE]

Over all training frames (posterior, as in training, and mean), per node:
  - sigma: the posterior standard deviation exp(logvar / 2), mean over frames and latent dimensions;
  - the between-frame spread of mu (std over frames, mean over dims) and its ratio to sigma: below ~1 the noise of
    a training step is larger than what tells two frames apart;
  - the between-frame spread of Delta n (RMS distance from the node's mean over frames, cm) with z = mu, and how
    much of Delta n changes when z = mu is replaced by z = 0 (RMS, cm): z's share of Delta n;
  - e: RMS of e_i, and ||W_e e_i|| / ||W_1 gamma(p_i) + b_1|| (the first-layer pre-activation of F_i split into its
    embedding and its coordinate parts, over local points drawn uniformly in each node's support ball).
With CAPTURE (synth, gt/geometry.npz): the same restricted to the nodes that hold skirt particles at frame 36.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch

from avatarctl.fit.checkpoint import load_avatar
from avatarctl.model.deformer import node_pose_condition
from avatarctl.model.encoding import positional_encoding
from avatarctl.project import Project


@torch.no_grad()
def main(project: Path, capture: Path | None = None) -> None:
    av = load_avatar(Project.open(project), device="cpu")
    m = av.model
    frames = sorted(int(f) for f in av.train_frames)
    cond = av.conditioning(av.capture.motion.select(av.capture.motion.rows_for(frames)), frames_are_training=True)
    theta = node_pose_condition(cond.pose_features.float(), m.pose_attention)
    post = m.latent(theta, cond.time.float(), cond.frame_ids, "mean")
    zero = m.latent(theta, cond.time.float(), cond.frame_ids, "zero")
    N = m.cfg.num_nodes
    sigma = torch.exp(0.5 * post.logvar).mean((0, 2))  # [N]
    mu_spread = post.mu.std(0).mean(-1)  # [N]
    dn = post.delta_n  # [T, N, 3]
    dn_spread = ((dn - dn.mean(0)) ** 2).sum(-1).mean(0).sqrt() * 100  # cm [N]
    dn_from_z = ((dn - zero.delta_n) ** 2).sum(-1).mean(0).sqrt() * 100  # cm [N]
    e_rms = post.embed.pow(2).mean((0, 2)).sqrt()  # [N]
    # first layer of F_i: W_1 gamma(p) + b_1 over points in the support ball vs W_e e_i
    g = torch.Generator().manual_seed(0)
    r = m._node_extent()
    p = torch.randn(N, 512, 3, generator=g)
    p = p / p.norm(dim=-1, keepdim=True) * r * torch.rand(N, 512, 1, generator=g) ** (1 / 3)
    ratio = torch.full((N,), float("nan"))
    if m.cfg.field == "mlp":
        first = m.fields.mlp.layers[0]
        coord = torch.bmm(positional_encoding(p, m.cfg.pe_coords), first.weight) + first.bias  # [N, 512, W]
        emb = m.fields.embed_bias(post.embed)  # [T, N, W]
        ratio = emb.norm(dim=-1).mean(0) / coord.norm(dim=-1).mean(1)
    sets = [("all nodes", torch.ones(N, dtype=torch.bool))]
    if capture is not None:
        from avatarctl.io.gt_geometry import load_gt_geometry
        from avatarctl.model.deformer import node_transforms

        geo = load_gt_geometry(capture / "gt" / "geometry.npz")
        x = torch.from_numpy(geo.garment_vertices[geo.row(36)]).double()
        t36 = frames.index(36)
        T = node_transforms(m.node_skin_weights.double(), cond.joint_transforms.double())[t36]  # [N, 4, 4]
        q = torch.einsum("nab,pb->npa", torch.linalg.inv(T)[:, :3, :3], x) + torch.linalg.inv(T)[:, None, :3, 3]
        q = q - m.node_rest.double()[:, None]
        skirt = ((q.norm(dim=-1) < m.cfg.support_radius).sum(1) >= 4)
        sets.append((f"skirt nodes ({int(skirt.sum())})", skirt))
    print(f"{project}: {len(frames)} training frames, {N} nodes, latent {m.cfg.latent}, "
          f"posterior_logvar_init {m.cfg.posterior_logvar_init}, pe_time {m.cfg.pe_time}")
    for name, s in sets:
        f = lambda v: float(v[s].mean())  # noqa: E731
        print(f"  {name:18s} sigma {f(sigma):.3f}  mu spread over frames {f(mu_spread):.4f} "
              f"(spread / sigma {f(mu_spread / sigma):.3f})  Delta n spread {f(dn_spread):.2f} cm, "
              f"z's part of Delta n {f(dn_from_z):.2f} cm  |e| rms {f(e_rms):.4f}  ||W_e e|| / ||W_1 g(p) + b|| "
              f"{float(np.nanmean(ratio[s].numpy())):.4f}")


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]) if len(sys.argv) > 2 else None)
