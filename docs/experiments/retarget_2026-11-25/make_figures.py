"""Figures and numbers for the issue-19 note: SMPL motion retargeted onto anny.

Run from the repository root (CPU, ~1 min):  python docs/experiments/retarget_2026-11-25/make_figures.py

Writes into this folder: `angle_errors.png` (bone direction error per joint group), `walk_sheet.png` (a retargeted
walk: source SMPL skeleton above, the anny body below), `numbers.json`.

SMPL model files are random files in the official npz format (tests/fixtures/smpl.py: never a licensed model):
- "random": random rest skeleton, random poses (sigma 0.35 rad), shape-aware retarget (the file is passed);
- "SMPL+H": random body and finger poses, the generic T-pose table (no model file) -> anny's fingers;
- "walk": rest joints placed in a T-pose (a person 1.08x the generic table), a procedural walk whose lowest foot
  joint touches the floor in every frame; retargeted shape-aware, and once more without the model file (the
  generic T-pose table stands in for the file's rest joints) but scored against the file's true joints.
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[3]
sys.path.insert(0, str(ROOT / "tests"))
OUT = Path(__file__).resolve().parent

from fixtures.smpl import grounded_smpl_walk, write_random_smpl_npz, write_t_pose_smpl_npz  # noqa: E402
from fixtures.tiny_project import paint  # noqa: E402

from avatarctl.body import rig_motion, rigs  # noqa: E402
from avatarctl.body.anny_model import AnnyBody  # noqa: E402
from avatarctl.body.motion import BodyMotion  # noqa: E402
from avatarctl.body.retarget import common_positions, direction_errors, floor_errors, retarget  # noqa: E402
from avatarctl.geometry.cameras import Camera, look_at  # noqa: E402

GROUPS = ("legs", "spine", "arms", "head", "hands")


def per_group(err) -> dict[str, dict[str, float]]:
    out = {}
    for g in GROUPS:
        cols = [i for i, gg in enumerate(err.groups) if gg == g]
        if cols:
            d = err.degrees[:, cols]
            out[g] = {"mean": float(d.mean()), "max": float(d.max()), "bones": len(cols)}
    out["all"] = {"mean": float(err.degrees.mean()), "max": float(err.degrees.max()), "bones": len(err.bones)}
    return out


def main() -> None:
    tmp = Path(tempfile.mkdtemp())
    anny_sk = rig_motion.skeleton_of("anny")
    numbers: dict = {}

    # ---- random poses of a random model ---------------------------------------------------------------------
    rnd_path = write_random_smpl_npz(tmp / "random.npz", "smpl", seed=1)
    rng = np.random.default_rng(2)
    F = 32
    m = BodyMotion(body_model="smpl", frame_index=np.arange(F), global_orient=rng.normal(0, 0.4, (F, 3)),
                   body_pose=rng.normal(0, 0.35, (F, 69)), transl=rng.normal(0, 0.3, (F, 3)),
                   betas=rng.normal(0, 1, 10))
    src = rig_motion.to_skeleton_motion(m, rig_motion.skeleton_of("smpl", m, rnd_path))
    out, _ = retarget(src, anny_sk)
    numbers["random_poses_shape_aware"] = per_group(direction_errors(src, out))

    # ---- SMPL+H with random finger poses (no model file: the generic table on both sides of the score) ----------
    hands = BodyMotion(body_model="smpl", frame_index=np.arange(F), global_orient=rng.normal(0, 0.4, (F, 3)),
                       body_pose=rng.normal(0, 0.35, (F, 69)), transl=np.zeros((F, 3)),
                       left_hand_pose=rng.normal(0, 0.35, (F, 45)), right_hand_pose=rng.normal(0, 0.35, (F, 45)))
    src_h = rig_motion.to_skeleton_motion(hands, rig_motion.skeleton_of("smpl", hands, hands=True))
    out_h, rep_h = retarget(src_h, anny_sk)
    numbers["smplh_fingers_generic_table"] = per_group(direction_errors(src_h, out_h))
    numbers["smplh_fingers_generic_table"]["joints_mapped"] = len(rep_h.mapped)

    # ---- a grounded walk, with and without the model file ------------------------------------------------------
    walk_path = write_t_pose_smpl_npz(tmp / "tpose.npz")
    walk = grounded_smpl_walk(walk_path, 48)
    truth = rig_motion.to_skeleton_motion(walk, rig_motion.skeleton_of("smpl", walk, walk_path))
    out_w, rep_w = retarget(truth, anny_sk)
    numbers["walk_shape_aware"] = per_group(direction_errors(truth, out_w))
    fe = floor_errors(truth, out_w, rep_w)
    numbers["walk_shape_aware"]["feet_height_error_cm"] = {"mean": float(fe.height_error.mean() * 100),
                                                           "max": float(fe.height_error.max() * 100)}
    numbers["walk_shape_aware"]["hip_track_error_cm_max"] = float(fe.root_error.max() * 100)
    numbers["walk_shape_aware"]["translation_scale"] = rep_w.scale
    generic = rig_motion.to_skeleton_motion(walk, rig_motion.skeleton_of("smpl"))
    out_g, _ = retarget(generic, anny_sk)
    # score against the true joints of the file: the generic table is only a stand-in for them
    numbers["walk_generic_table"] = per_group(direction_errors(truth, out_g))
    fe_g = floor_errors(truth, out_g, rep_w)
    numbers["walk_generic_table"]["feet_height_error_cm"] = {"mean": float(fe_g.height_error.mean() * 100),
                                                             "max": float(fe_g.height_error.max() * 100)}
    (OUT / "numbers.json").write_text(json.dumps(numbers, indent=2) + "\n")
    print(json.dumps(numbers, indent=2))

    # ---- figure 1: angle errors per joint group ------------------------------------------------------------------
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cases = [("random poses,\nmodel file", "random_poses_shape_aware"), ("walk,\nmodel file", "walk_shape_aware"),
             ("walk, no model file (generic\nT-pose table vs the file's joints)", "walk_generic_table"),
             ("SMPL+H random poses with fingers,\ngeneric table", "smplh_fingers_generic_table")]
    fig, ax = plt.subplots(figsize=(7.5, 3.2), dpi=100)
    w = 0.2
    for k, (label, key) in enumerate(cases):
        means = [numbers[key].get(g, {}).get("mean", 0.0) for g in GROUPS]
        maxs = [numbers[key].get(g, {}).get("max", 0.0) for g in GROUPS]
        x = np.arange(len(GROUPS)) + (k - 1.5) * w
        ax.bar(x, means, w, label=label.replace("\n", " "))
        ax.scatter(x, maxs, marker="_", s=120, color="k", zorder=3)
    ax.set_yscale("log")
    ax.set_ylim(1e-8, 1e5)  # room for the legend above the bars
    ax.axhline(5.0, color="r", lw=0.8, ls="--")
    ax.text(len(GROUPS) - 0.5, 6.0, "5° target", color="r", ha="right", fontsize=8)
    ax.set_xticks(np.arange(len(GROUPS)), GROUPS)
    ax.set_ylabel("bone direction error (deg, log)\nbar: mean, tick: max")
    ax.set_title("SMPL -> anny: world direction of each mapped bone vs SMPL's", fontsize=10)
    ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    fig.savefig(OUT / "angle_errors.png")
    plt.close(fig)

    # ---- figure 2: contact sheet of the retargeted walk ----------------------------------------------------------
    body = AnnyBody()
    bm = rig_motion.to_body_motion(out_w, "anny")
    verts = body.run(bm)["vertices"].numpy()  # [frames, V, 3] anny world (z up)
    faces = body.faces().numpy()
    src_P = common_positions(truth)  # [frames, 24, 3] common frame (z up), the source's own floor at 0
    tgt_P = common_positions(out_w)
    frames = np.linspace(0, 46, 6).astype(int)
    size = 220
    sheet_rows = [[], []]
    for f in frames:
        centre_t = tgt_P[f, 0] * np.array([1, 1, 0]) + np.array([0, 0, -0.1])
        centre_s = src_P[f, 0] * np.array([1, 1, 0]) + np.array([0, 0, 0.8])
        for row, centre, kind in ((0, centre_s, "skeleton"), (1, centre_t, "mesh")):
            eye = centre + np.array([2.6, -1.0, 0.3])  # from the subject's left, a little in front
            R, T = look_at(eye, centre)
            fpx = size * 1.5
            cam = Camera(name="side", K=np.array([[fpx, 0, size / 2], [0, fpx, size / 2], [0, 0, 1]]), R=R, T=T,
                         width=size, height=size)
            if kind == "mesh":
                v = verts[f]
                n = np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]])
                n /= np.linalg.norm(n, axis=1, keepdims=True) + 1e-12
                light = (eye - centre) / np.linalg.norm(eye - centre)
                shade = (60 + 180 * np.clip(np.abs(n @ light), 0, 1)).astype(np.uint8)
                colours = np.stack([shade, (shade * 0.85).astype(np.uint8), (shade * 0.75).astype(np.uint8)], 1)
                img, _ = paint(cam, verts[f], faces, colours)
            else:
                img = draw_skeleton(cam, src_P[f], truth.skeleton.parents)
            img[np.all(img == 0, axis=-1)] = 255
            sheet_rows[row].append(img)
    import cv2

    sheet = np.concatenate([np.concatenate(r, axis=1) for r in sheet_rows], axis=0)
    for i, f in enumerate(frames):
        cv2.putText(sheet, f"frame {f}", (i * size + 6, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1)
    cv2.putText(sheet, "source: SMPL skeleton (model file)", (6, size - 8), cv2.FONT_HERSHEY_SIMPLEX, 0.4,
                (0, 0, 160), 1)
    cv2.putText(sheet, "retargeted onto anny", (6, 2 * size - 8), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 160), 1)
    cv2.imwrite(str(OUT / "walk_sheet.png"), sheet[..., ::-1], [cv2.IMWRITE_PNG_COMPRESSION, 9])
    print("wrote", OUT / "angle_errors.png", OUT / "walk_sheet.png")


def draw_skeleton(cam: Camera, P: np.ndarray, parents: tuple[int, ...]) -> np.ndarray:
    """Joints [J, 3] (common frame) as coloured bones on black: left side blue, right side red, centre grey."""
    import cv2

    img = np.zeros((cam.height, cam.width, 3), np.uint8)
    uv = cam.project(P, distort=False)
    for j, p in enumerate(parents):
        if p < 0:
            continue
        name = rigs.SMPL_NAMES[j]
        colour = (40, 80, 220) if name.startswith("left") else (220, 60, 40) if name.startswith("right") else \
            (90, 90, 90)
        cv2.line(img, tuple(np.round(uv[p]).astype(int)), tuple(np.round(uv[j]).astype(int)), colour, 2,
                 cv2.LINE_AA)
    for q in uv:
        cv2.circle(img, tuple(np.round(q).astype(int)), 2, (20, 20, 20), -1, cv2.LINE_AA)
    floor = np.array([[P[0, 0] + dx, P[0, 1] + dy, 0.0] for dx, dy in ((-0.6, -0.6), (0.6, 0.6))])
    a, b = cam.project(floor, distort=False)
    cv2.line(img, tuple(np.round(a).astype(int)), tuple(np.round(b).astype(int)), (150, 150, 150), 1)
    return img


if __name__ == "__main__":
    main()
