"""Issue 18, hypothesis 3 as a training oracle: node translations from the ground-truth skirt motion, frozen.

Not part of the package. Two sub-commands:

    python oracle.py table PROJECT CAPTURE OUT.npz [REF_FRAME]
        PROJECT: a fitted synth-small project (any number of steps: only its nodes are read; a fit with the same
        seed and config places the same nodes). For every node i with >= 4 skirt particles (gt/geometry.npz) in
        its support at REF_FRAME (default 36) and every training frame t: Delta n_i(t) = the mean, over those
        particles, of q_t - q_ref, where q is the particle in node i's canonical frame (T_i(t)^-1 x - n_bar_i,
        Eq. 1 / Eq. 4 without Delta n): the best per-frame translation of the node (least squares), i.e. what a
        perfect Delta n would be. Writes delta_n [T, N, 3] (metres, canonical), has [N] bool.
    python oracle.py run TABLE.npz [--add] -- avatarctl ARGS...
        Runs the avatarctl CLI with `SlrfAvatar.node_state` patched: for training frames (frame_ids >= 0) the nodes
        that have an oracle take it as their Delta n (frozen: no gradient; with --add it is added to the learned
        Delta n), the other nodes keep the learned Delta n. Novel poses (frame_ids < 0) are left as the model gives
        them. Use it for `fit` and for `eval` (the checkpoint does not hold the table).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch


def table(project: Path, capture: Path, out: Path, ref: int = 36) -> None:
    from avatarctl.fit.checkpoint import load_avatar
    from avatarctl.io.gt_geometry import load_gt_geometry
    from avatarctl.model.deformer import node_transforms
    from avatarctl.project import Project

    av = load_avatar(Project.open(project), device="cpu")
    m = av.model
    frames = sorted(int(f) for f in av.train_frames)
    cond = av.conditioning(av.capture.motion.select(av.capture.motion.rows_for(frames)), frames_are_training=True)
    geo = load_gt_geometry(capture / "gt" / "geometry.npz")
    X = geo.garment_vertices[[geo.row(f) for f in frames]].astype(np.float64)  # [T, P, 3]
    T = node_transforms(m.node_skin_weights.double(), cond.joint_transforms.double()).numpy()  # [T, N, 4, 4]
    Tinv = np.linalg.inv(T)
    rest = m.node_rest.double().numpy()
    radius, t0 = m.cfg.support_radius, frames.index(ref)
    N = rest.shape[0]
    delta = np.zeros((len(frames), N, 3))
    has = np.zeros(N, bool)
    for i in range(N):
        q = np.einsum("fab,fpb->fpa", Tinv[:, i, :3, :3], X) + Tinv[:, i, None, :3, 3] - rest[i]  # [T, P, 3]
        inside = np.linalg.norm(q[t0], axis=-1) < radius
        if inside.sum() < 4:
            continue
        has[i] = True
        delta[:, i] = (q[:, inside] - q[t0, inside][None]).mean(1)
    rms = np.sqrt((delta[:, has] ** 2).sum(-1).mean()) * 100 if has.any() else 0.0
    np.savez(out, delta_n=delta.astype(np.float32), has=has, frames=np.array(frames), ref=ref)
    print(f"{int(has.sum())} of {N} nodes hold skirt particles at frame {ref}; oracle |Delta n| RMS {rms:.2f} cm "
          f"over {len(frames)} training frames -> {out}")


def run(tab: Path, add: bool, argv: list[str]) -> None:
    from avatarctl.model.avatar import SlrfAvatar
    from avatarctl.model.deformer import posed_node_centers

    data = np.load(tab)
    oracle, has = torch.from_numpy(data["delta_n"]), torch.from_numpy(data["has"])
    original = SlrfAvatar.node_state

    def node_state(self, cond, mode, generator=None):
        state = original(self, cond, mode, generator)
        fid = cond.frame_ids.to(state.delta_n.device)
        if (fid < 0).all():
            return state
        o = oracle.to(state.delta_n)[fid.clamp(min=0)]  # [B, N, 3]
        use = (has.to(o.device)[None, :, None] & (fid >= 0)[:, None, None])
        delta = torch.where(use, o + state.delta_n if add else o, state.delta_n)
        state.delta_n = delta
        state.centers = posed_node_centers(state.transforms, self.node_rest, delta.to(state.transforms.dtype))
        return state

    SlrfAvatar.node_state = node_state
    from avatarctl.cli.app import main

    sys.argv = ["avatarctl", *argv]
    main()


if __name__ == "__main__":
    if sys.argv[1] == "table":
        table(Path(sys.argv[2]), Path(sys.argv[3]), Path(sys.argv[4]), *(int(a) for a in sys.argv[5:]))
    elif sys.argv[1] == "run":
        rest = sys.argv[3:]
        add = "--add" in rest[: rest.index("--")]
        run(Path(sys.argv[2]), add, rest[rest.index("--") + 1:])
    else:
        raise SystemExit(__doc__)
