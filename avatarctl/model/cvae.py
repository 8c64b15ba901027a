"""Per-node conditional VAEs (Sec. 4.1, Eq. 9-10): node-related variables (Delta n_i, e_i) from time and pose.

Encoder  E_i(gamma(t/T), theta_i) -> (mu_i, log sigma_i^2)   (Eq. 9, m = pe_time for the time stamp)
Decoder  D_i(z_i, theta_i)        -> (Delta n_i, e_i)          (Eq. 10)

Both are N parallel tiny MLPs (two ReLU layers of `cvae_width`), batched over the `nodes` dimension.
Latent variants (`ModelConfig.latent`):
- "cvae": as above.
- "deterministic": no encoder, no z, no KL: D_i(theta_i) regresses the node variables from the pose alone.
- "per_frame": a learnable code c_t per training frame (width of gamma(t), shared by all nodes, init N(0, 0.01^2))
  replaces gamma(t/T) as the encoder input; the rest is the cVAE.
Inference modes: "posterior" z = mu + sigma * eps (reparameterised, training); "mean" z = mu (training frames at test);
"zero" z = 0, encoder skipped; "novel" the latent of novel poses, encoder skipped: z = 0 (paper Sec. 4.1), or with
`novel_latent = "train_mean"` (a deviation) z_i = the mean over all training frames of the posterior means mu_i
(`latent_mean`, set by `set_latent_mean` from the weights of the moment: the fit does it before every checkpoint);
"sample" z ~ N(0, I) from the given generator.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from avatarctl.model.batched_mlp import BatchedMLP
from avatarctl.model.config import ModelConfig
from avatarctl.model.encoding import encoded_dim, positional_encoding

MODES = ("posterior", "mean", "zero", "novel", "sample")


@dataclass
class NodeVariables:
    delta_n: torch.Tensor  # [frames, N, 3] canonical residual translation, metres (raw decoder output)
    embed: torch.Tensor  # [frames, N, E]
    mu: torch.Tensor | None  # [frames, N, Z], None when the encoder did not run
    logvar: torch.Tensor | None  # [frames, N, Z]


class NodeCVAE(nn.Module):
    def __init__(self, cfg: ModelConfig, num_joints: int, num_frames: int):
        super().__init__()
        self.cfg = cfg
        N, Z, W = cfg.num_nodes, cfg.latent_dim, cfg.cvae_channels
        cond = 3 * num_joints
        time_dim = encoded_dim(1, cfg.pe_time)
        self.num_frames = num_frames
        if cfg.latent == "per_frame":
            self.frame_codes = nn.Parameter(0.01 * torch.randn(max(num_frames, 1), time_dim))  # [frames, C]
        if cfg.latent in ("cvae", "per_frame"):
            self.encoder = BatchedMLP(N, [time_dim + cond, W, W, 2 * Z])
            dec_in = Z + cond
        else:
            self.encoder = None
            dec_in = cond
        if cfg.novel_latent == "train_mean" and self.encoder is not None:
            self.register_buffer("latent_mean", torch.zeros(N, Z))  # [N, Z] mean of mu_i over the training frames
        # small initial outputs: nodes start on the body (Delta n ~ 1e-3 m) with near-zero embeddings
        self.decoder = BatchedMLP(N, [dec_in, W, W, 3 + cfg.embed_dim], last_init_scale=0.01)

    def _encoder_input(self, time: torch.Tensor, frame_ids: torch.Tensor) -> torch.Tensor:
        """[frames] -> [frames, C]: gamma(t/T), or the learnable code of each frame ("per_frame")."""
        if self.cfg.latent == "per_frame":
            if (frame_ids < 0).any() or (frame_ids >= self.num_frames).any():
                raise ValueError(f"latent 'per_frame' needs training frame ids in [0, {self.num_frames}) for this "
                                 f"mode, got {frame_ids.tolist()}; use mode 'zero' for novel poses")
            return self.frame_codes[frame_ids]
        return positional_encoding(time[:, None].to(self.decoder.layers[0].weight.dtype), self.cfg.pe_time)

    def forward(self, theta_i: torch.Tensor, time: torch.Tensor, frame_ids: torch.Tensor, mode: str,
                generator: torch.Generator | None = None) -> NodeVariables:
        """theta_i [frames, N, 3J] (Eq. 8), time [frames] in [0, 1], frame_ids [frames] long -> NodeVariables."""
        if mode not in MODES:
            raise ValueError(f"unknown mode {mode!r}; use one of {MODES}")
        B, N, _ = theta_i.shape
        Z = self.cfg.latent_dim
        cond = theta_i.transpose(0, 1)  # [N, frames, 3J]
        mu = logvar = None
        if self.encoder is None:
            dec_in = cond
        else:
            if mode in ("posterior", "mean"):
                x = self._encoder_input(time, frame_ids)  # [frames, C]
                x = torch.cat([x[None].expand(N, B, x.shape[-1]), cond], dim=-1)
                stats = self.encoder(x)  # [N, frames, 2Z]
                mu, logvar = stats[..., :Z], stats[..., Z:].clamp(-20.0, 10.0)
                if mode == "posterior":
                    eps = _randn(mu.shape, generator, mu)
                    z = mu + torch.exp(0.5 * logvar) * eps
                else:
                    z = mu
                mu, logvar = mu.transpose(0, 1), logvar.transpose(0, 1)
            elif mode == "zero" or (mode == "novel" and not hasattr(self, "latent_mean")):
                z = cond.new_zeros(N, B, Z)
            elif mode == "novel":
                z = self.latent_mean.to(cond)[:, None].expand(N, B, Z)
            else:  # sample from the prior
                z = _randn((N, B, Z), generator, cond)
            dec_in = torch.cat([z, cond], dim=-1)
        out = self.decoder(dec_in).transpose(0, 1)  # [frames, N, 3 + E]
        return NodeVariables(delta_n=out[..., :3], embed=out[..., 3:], mu=mu, logvar=logvar)

    @torch.no_grad()
    def set_latent_mean(self, theta_i: torch.Tensor, time: torch.Tensor, frame_ids: torch.Tensor,
                        chunk: int = 256) -> None:
        """`latent_mean` := the mean over the given (all training) frames of the posterior means mu_i ("train_mean").
        theta_i [frames, N, 3J] (Eq. 8), time [frames], frame_ids [frames]."""
        total = sum(self(theta_i[s:s + chunk], time[s:s + chunk], frame_ids[s:s + chunk], "mean").mu.float().sum(0)
                    for s in range(0, theta_i.shape[0], chunk))  # mu [chunk, N, Z] summed over frames -> [N, Z]
        self.latent_mean.copy_(total / theta_i.shape[0])

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        # a checkpoint without the mean (trained before it existed): z = 0, the paper's novel-pose latent
        if hasattr(self, "latent_mean") and prefix + "latent_mean" not in state_dict:
            state_dict[prefix + "latent_mean"] = torch.zeros_like(self.latent_mean)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)


def _randn(shape: tuple[int, ...] | torch.Size, generator: torch.Generator | None, like: torch.Tensor) -> torch.Tensor:
    """Standard normal noise drawn on the generator's device (so a CPU generator seeds CUDA runs too)."""
    dev = generator.device if generator is not None else like.device
    return torch.randn(tuple(shape), generator=generator, device=dev, dtype=like.dtype).to(like.device)
