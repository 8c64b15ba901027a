"""Issue 18, hypothesis 1's side effect on novel poses: z = 0 (the paper) vs z = the mean posterior mean.

Not part of the package. With a narrow posterior (`model.posterior_logvar_init` -6) the decoder learns on z = mu,
and mu is not pulled to 0 (lambda_KL = 1e-5), so z = 0 at a novel pose is a latent the decoder never saw.

    python zmean.py PROJECT -- avatarctl eval PROJECT --split novel_pose ... --name NAME

runs the avatarctl CLI with the novel-pose latent modes ("zero", "novel") patched to z_i = the mean of mu_i over all
training frames (per node), computed once from the project's training poses and time stamps.
"""

from __future__ import annotations

import sys
from pathlib import Path

import torch


def main(project: Path, argv: list[str]) -> None:
    from avatarctl.fit.checkpoint import load_avatar
    from avatarctl.model.cvae import NodeCVAE
    from avatarctl.model.deformer import node_pose_condition
    from avatarctl.project import Project

    av = load_avatar(Project.open(project), device="cpu")
    m = av.model
    frames = sorted(int(f) for f in av.train_frames)
    cond = av.conditioning(av.capture.motion.select(av.capture.motion.rows_for(frames)), frames_are_training=True)
    with torch.no_grad():
        theta = node_pose_condition(cond.pose_features.float(), m.pose_attention)
        mu_mean = m.latent(theta, cond.time.float(), cond.frame_ids, "mean").mu.mean(0)  # [N, Z]
    print(f"mean posterior mean over {len(frames)} training frames: |z| RMS {float(mu_mean.pow(2).mean().sqrt()):.3f}")
    original = NodeCVAE.forward

    def forward(self, theta_i, time, frame_ids, mode, generator=None):
        if mode not in ("zero", "novel"):  # "novel": what --latent auto gives novel poses since novel_latent
            return original(self, theta_i, time, frame_ids, mode, generator)
        B = theta_i.shape[0]
        z = mu_mean.to(theta_i)[:, None].expand(-1, B, -1)  # [N, B, Z]
        out = self.decoder(torch.cat([z, theta_i.transpose(0, 1)], dim=-1)).transpose(0, 1)
        from avatarctl.model.cvae import NodeVariables

        return NodeVariables(delta_n=out[..., :3], embed=out[..., 3:], mu=None, logvar=None)

    NodeCVAE.forward = forward
    from avatarctl.cli.app import main as cli

    sys.argv = ["avatarctl", *argv]
    cli()


if __name__ == "__main__":
    main(Path(sys.argv[1]), sys.argv[sys.argv.index("--") + 1:])
