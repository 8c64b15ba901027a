"""How far the skirt's material points drift in the local frames of the nodes that own them (issue 18, hyp. 3).

Not part of the package. Needs a fitted synth-small project (for its nodes and body conditioning) and its synth
capture (gt/geometry.npz: the simulated skirt particles, one fixed material point each, so a texture point).

For every node i and every training frame t, the skirt particles inside node i's support at a reference frame t0
are expressed in node i's local frame at t0 and at t (q0, qt, Eq. 4 without Delta n). Their drift is qt - q0: what
a canonical local field would have to absorb (a fixed field with no per-frame change blurs the print by it).
Residual drift after the best per-frame correction of each node:
  - none       : the node frame of the skinning alone (Delta n = 0)
  - translation: the best per-frame translation of the node (what Delta n can do: least squares = mean offset)
  - rigid      : the best per-frame rotation + translation (Kabsch), i.e. a per-node residual rotation beside Delta n
for node frames from (a) the template's skinning weights, (b) the same nodes re-assigned to the pelvis (root
joint) when their weights are mostly on the legs. RMS in cm, over (node, particle, frame), particles that stay
inside the node's support at t only ("lost" = share that left it: hyp. 2).

    python skirt_drift.py PROJECT CAPTURE [REF_FRAME [RADIUS_MM]]   # default: the model's support radius
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch

from avatarctl.fit.checkpoint import load_avatar
from avatarctl.io.gt_geometry import load_gt_geometry
from avatarctl.project import Project


def kabsch_residual(P: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """Residual Q - (R P + t) of the best rigid map P -> Q ([K, 3] each)."""
    pc, qc = P.mean(0), Q.mean(0)
    H = (P - pc).T @ (Q - qc)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    R = Vt.T @ np.diag([1, 1, d]) @ U.T
    return Q - ((P - pc) @ R.T + qc)


def main(project: Path, capture: Path, ref: int = 36, radius_mm: int = 0) -> None:
    av = load_avatar(Project.open(project), device="cpu")
    m, body = av.model, av.body
    geo = load_gt_geometry(capture / "gt" / "geometry.npz")
    frames = sorted(int(f) for f in av.train_frames)
    motion = av.capture.motion.select(av.capture.motion.rows_for(frames))
    cond = av.conditioning(motion, frames_are_training=True)
    names = list(body.joint_names)
    W = m.node_skin_weights.clone()  # [N, J]
    leg = torch.tensor([("leg" in n) for n in names])
    on_legs = W[:, leg].sum(1) > 0.5
    root = names.index("root")
    W_pelvis = W.clone()
    W_pelvis[on_legs] = 0.0
    W_pelvis[on_legs, root] = 1.0
    M = cond.joint_transforms.double()  # [F, J, 4, 4]
    rest = m.node_rest.double().numpy()  # [N, 3]
    radius = radius_mm / 1000 if radius_mm else m.cfg.support_radius
    g_rows = [geo.row(f) for f in frames]
    X = geo.garment_vertices[g_rows].astype(np.float64)  # [F, P, 3]
    t0 = frames.index(ref)
    print(f"{len(frames)} training frames, reference frame {ref}, support radius {radius * 100:.1f} cm; {int(on_legs.sum())} of {len(W)} nodes have "
          f"> 50 % of their skinning weight on leg bones")
    for label, weights in (("template skinning", W), ("leg nodes -> pelvis (root)", W_pelvis)):
        T = torch.einsum("nj,fjab->fnab", weights.double(), M).numpy()  # [F, N, 4, 4] Eq. 1
        Tinv = np.linalg.inv(T)
        acc = {"none": [], "translation": [], "rigid": []}
        per_frame = {k: [[] for _ in frames] for k in acc}
        lost = kept = 0
        for i in range(len(W)):
            # particles inside node i's support at the reference frame
            q_all = np.einsum("fab,fpb->fpa", Tinv[:, i, :3, :3], X) + Tinv[:, i, None, :3, 3] - rest[i]  # [F, P, 3]
            inside0 = np.linalg.norm(q_all[t0], axis=-1) < radius
            if inside0.sum() < 4:
                continue
            q0 = q_all[t0, inside0]
            for f in range(len(frames)):
                qt = q_all[f, inside0]
                ok = np.linalg.norm(qt, axis=-1) < radius
                lost += int((~ok).sum())
                kept += int(ok.sum())
                if ok.sum() < 4:
                    continue
                d = qt[ok] - q0[ok]
                for k, r in (("none", d), ("translation", d - d.mean(0)), ("rigid", kabsch_residual(q0[ok], qt[ok]))):
                    acc[k].append(r)
                    per_frame[k][f].append(r)
        rms = {k: 100 * float(np.sqrt(np.mean(np.concatenate(v) ** 2) * 3)) for k, v in acc.items()}
        print(f"{label:28s} drift RMS (cm): none {rms['none']:.2f}  best translation {rms['translation']:.2f}  "
              f"best rigid {rms['rigid']:.2f}; particles that left the support: {lost / (lost + kept):.1%}")
        segs = [(a, min(a + 10, len(frames))) for a in range(0, len(frames), 10)]
        print("    per 10 training frames, translation / rigid residual RMS (cm): " + "  ".join(
            f"{frames[a]}-{frames[b - 1]}: " + "/".join(
                f"{100 * float(np.sqrt(np.mean(np.concatenate([r for f in range(a, b) for r in per_frame[k][f]]) ** 2) * 3)):.1f}"
                for k in ("translation", "rigid")) for a, b in segs))


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]), *(int(a) for a in sys.argv[3:]))
