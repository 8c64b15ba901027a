"""How well does the body pose determine the skirt? (issue 18: can a pose-conditioned avatar put the print right at
novel poses?)

For every frame, the skirt particles and body vertices are expressed in the waist frame (the rigid motion that best
maps the skirt's attached top ring of frame 0 onto that frame's, Kabsch). For each test frame we take the training
frame whose body (all vertices, waist frame) is nearest, and report how far the same skirt material points are apart
(RMS, cm): a pose-conditioned model that interpolates the training frames perfectly could at best put the print
there, while the tartan's fine stripes have a 3.7 cm period and the garment target needs < ~2 px (~2 cm) accuracy.
Reference rows: consecutive training frames, and the mean training skirt.

    python pose_determinism.py CAPTURE        # an `avatarctl synth` output (gt/geometry.npz, split.json)
"""

from __future__ import annotations

import json
import sys

import numpy as np


def kabsch(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """R, t minimising |R a + t - b| over corresponding rows of a, b [K, 3]."""
    ca, cb = a.mean(0), b.mean(0)
    u, _, vt = np.linalg.svd((a - ca).T @ (b - cb))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    r = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return r, cb - r @ ca


def main(capture: str) -> None:
    g = np.load(f"{capture}/gt/geometry.npz")
    split = json.load(open(f"{capture}/split.json"))
    skirt = g["garment_vertices"].astype(np.float64)  # [F, P, 3]
    body = g["body_vertices"].astype(np.float64)
    param = g["garment_param"]
    top = np.where(param[:, 1] <= param[:, 1].min() + 1e-6)[0]
    nf = skirt.shape[0]
    sk_w = np.empty_like(skirt)
    bo_w = np.empty_like(body)
    rots, cens = np.empty((nf, 3, 3)), np.empty((nf, 3))
    for f in range(nf):  # into the waist frame of frame 0
        r, t = kabsch(skirt[f, top], skirt[0, top])
        rots[f], cens[f] = r, skirt[f, top].mean(0)
        sk_w[f] = skirt[f] @ r.T + t
        bo_w[f] = body[f] @ r.T + t
    train, test = np.asarray(split["train_frames"]), np.asarray(split["test_frames"])

    def rms(a: np.ndarray, b: np.ndarray) -> float:
        return float(np.sqrt(((a - b) ** 2).sum(-1).mean()) * 100)

    hem = param[:, 1] >= 0.75  # the lowest quarter
    lines = []
    near_s, near_h, near_b = [], [], []
    for f in test:
        db = [rms(bo_w[f], bo_w[k]) for k in train]
        k = train[int(np.argmin(db))]
        near_b.append(min(db))
        near_s.append(rms(sk_w[f], sk_w[k]))
        near_h.append(rms(sk_w[f, hem], sk_w[k, hem]))
    mean_sk = sk_w[train].mean(0)
    cons = [rms(sk_w[a], sk_w[a + 1]) for a in train[:-1]]
    lines.append(f"test frames {len(test)}: nearest-pose training frame: body {np.mean(near_b):.2f} cm, "
                 f"skirt {np.mean(near_s):.2f} cm (hem quarter {np.mean(near_h):.2f}; median skirt "
                 f"{np.median(near_s):.2f}, max {np.max(near_s):.2f})")
    lines.append(f"mean training skirt vs test frames: {np.mean([rms(sk_w[f], mean_sk) for f in test]):.2f} cm; "
                 f"vs training frames {np.mean([rms(sk_w[f], mean_sk) for f in train]):.2f} cm")
    # a learned pose -> skirt map: ridge regression from the body's principal components (training frames)
    xb = bo_w.reshape(nf, -1)
    mu = xb[train].mean(0)
    _, _, vt = np.linalg.svd(xb[train] - mu, full_matrices=False)
    ys = sk_w.reshape(nf, -1)
    ym = ys[train].mean(0)
    # the waist's motion (history the pose does not carry): angular velocity (rad/frame, waist frame) and linear
    # velocity of the waist centre (m/frame, waist frame), backward differences (frame 0 / 80: forward)
    vel = np.zeros((nf, 6))
    for f in range(nf):
        p = f - 1 if f not in (train[0], test[0]) else f + 1
        dr = rots[f] @ rots[p].T  # frame p's waist -> frame f's, in the frame-0 waist coordinates
        ang = np.arccos(np.clip((np.trace(dr) - 1) / 2, -1, 1))
        axis = np.array([dr[2, 1] - dr[1, 2], dr[0, 2] - dr[2, 0], dr[1, 0] - dr[0, 1]])
        omega = axis / max(np.linalg.norm(axis), 1e-12) * ang
        vel[f] = np.r_[omega, rots[f] @ (cens[f] - cens[p])] * (1 if p < f else -1)
    speed = np.c_[np.linalg.norm(vel[:, :3], axis=1), np.linalg.norm(vel[:, 3:], axis=1)]  # |omega|, |v|
    for comps, use_vel in ((5, ""), (10, ""), (20, ""), (5, "velocities"), (20, "velocities"), (20, "speeds")):
        feat = (xb - mu) @ vt[:comps].T  # centred on the training frames; the intercept (ym) is not penalised
        if use_vel:  # velocities: omega and v (signed, 6); speeds: their magnitudes (2: a twirl either way)
            v = vel if use_vel == "velocities" else speed
            v = v / v[train].std(0).clip(1e-9) * feat[train].std()
            feat = np.c_[feat, v - v[train].mean(0)]
        a = feat[train]
        best = None
        for lam in 10.0 ** np.arange(-4, 7):
            w = np.linalg.solve(a.T @ a + lam * np.eye(a.shape[1]), a.T @ (ys[train] - ym))
            pred = feat @ w + ym
            err = np.mean([rms(pred[f].reshape(-1, 3), sk_w[f]) for f in test])
            fit = np.mean([rms(pred[f].reshape(-1, 3), sk_w[f]) for f in train])
            if best is None or err < best[0]:
                best = (err, lam, fit)
        extra = f" + waist {use_vel}" if use_vel else ""
        lines.append(f"ridge pose->skirt, {comps} body components{extra} (best lambda {best[1]:g} chosen on the test "
                     f"frames, an optimistic bound): test skirt {best[0]:.2f} cm, training frames {best[2]:.2f} cm")
    # one pose, several skirts: within the training frames, each frame's nearest other frame by body (at least 5
    # frames apart) and how far their skirts are
    twins = []
    for f in train:
        others = [k for k in train if abs(int(k) - int(f)) >= 5]
        db = [rms(bo_w[f], bo_w[k]) for k in others]
        k = others[int(np.argmin(db))]
        twins.append((min(db), rms(sk_w[f], sk_w[k])))
    tw = np.asarray(twins)
    close = tw[tw[:, 0] < 3.0, 1]  # skirt distances of the pairs whose bodies are < 3 cm apart
    c_mean, c_max = (close.mean(), close.max()) if len(close) else (float("nan"), float("nan"))
    lines.append(f"training frames' nearest body >= 5 frames apart: body {tw[:, 0].mean():.2f} cm, skirt "
                 f"{tw[:, 1].mean():.2f} cm; the {len(close)} pairs with bodies < 3 cm apart: skirt "
                 f"{c_mean:.2f} cm (max {c_max:.2f})")
    lines.append(f"consecutive training frames: skirt {np.mean(cons):.2f} cm per frame")
    print("\n".join(lines))


if __name__ == "__main__":
    main(sys.argv[1])
