"""A self-contained HTML page that plays a short motion of a Gaussian-field avatar without Python
(`avatarctl export --format player`): the per-frame columns of the 3DGS `.ply` export (`export.splat_ply.splat_arrays`)
packed into the page, drawn by a small WebGL2 splat renderer of our own (`export/player_page.py`).

Packing (little-endian; one gzip'd, base64 block in the page; G_f Gaussians in frame f, opacity >= 1/255 kept):
    header: uint32 length + UTF-8 JSON {frames, fps, counts, lo, hi, up, target, radius, labels, log_scale,
            low_pass}
    per frame, per Gaussian:
      position  3 x uint16, quantised in the box [lo, hi] of all frames (metres; step (hi - lo) / 65535)
      rotation  4 x int8, the unit quaternion (w, x, y, z) of the `.ply` `rot_*` times 127
      scales    3 x uint8, log-scales (`.ply` `scale_*`) quantised over [LOG_SCALE_MIN, LOG_SCALE_MAX]
      colour    4 x uint8, RGB = 0.5 + 0.28209479 f_dc (the DC band: no view dependence), A = sigmoid(opacity)
    = 17 bytes a Gaussian (the `.ply` row holds 248).
The page rebuilds each covariance R S^2 R^T, sorts the Gaussians back to front when the view or frame changes, and
composits them with the 3DGS splat equations (EWA projection, the avatar's low-pass `model.gaussians.low_pass` in
px^2 from the header, 3 sigma quads).
"""

from __future__ import annotations

import base64
import gzip
import json
from pathlib import Path

import numpy as np

from avatarctl.atomic import atomic_path

LOG_SCALE_MIN, LOG_SCALE_MAX = -12.0, 0.0  # log metres: 6 micrometres .. 1 metre
SH_C0 = 0.28209479177387814
BYTES_PER_GAUSSIAN = 17


def pack_frames(columns: list[dict[str, np.ndarray]], fps: float, up: np.ndarray, labels: list[str],
                low_pass: float, min_opacity: float = 1.0 / 255.0) -> bytes:
    """The packed block of the module docstring from `splat_arrays` columns of each frame (world frame, metres);
    `low_pass` px^2, the avatar's (`model.gaussians.low_pass`)."""
    if not columns:
        raise ValueError("the player needs at least one frame")
    keep = [1.0 / (1.0 + np.exp(-c["opacity"].astype(np.float64))) >= min_opacity for c in columns]
    xyz = [c["xyz"][k].astype(np.float64) for c, k in zip(columns, keep)]
    allxyz = np.concatenate(xyz) if sum(len(x) for x in xyz) else np.zeros((1, 3))
    lo, hi = allxyz.min(0), allxyz.max(0)
    hi = np.maximum(hi, lo + 1e-6)
    parts = []
    for c, k, p in zip(columns, keep, xyz):
        pos = np.round((p - lo) / (hi - lo) * 65535).clip(0, 65535).astype("<u2")
        rot = c["rot"][k].astype(np.float64)
        rot = rot / np.maximum(np.linalg.norm(rot, axis=1, keepdims=True), 1e-12)
        q = np.round(rot * 127).clip(-127, 127).astype(np.int8)
        s = np.round((c["scale"][k] - LOG_SCALE_MIN) / (LOG_SCALE_MAX - LOG_SCALE_MIN) * 255).clip(0, 255)
        rgb = (0.5 + SH_C0 * c["f_dc"][k].astype(np.float64)).clip(0, 1)
        a = 1.0 / (1.0 + np.exp(-c["opacity"][k].astype(np.float64)))
        rgba = np.round(np.concatenate([rgb, a[:, None]], 1) * 255).clip(0, 255).astype(np.uint8)
        parts += [pos.tobytes(), q.tobytes(), s.astype(np.uint8).tobytes(), rgba.tobytes()]
    centre = (lo + hi) / 2
    header = {"frames": len(columns), "fps": float(fps), "counts": [int(k.sum()) for k in keep],
              "lo": lo.tolist(), "hi": hi.tolist(), "up": np.asarray(up, float).tolist(), "target": centre.tolist(),
              "radius": float(np.linalg.norm(hi - lo)) * 1.2, "labels": list(labels),
              "log_scale": [LOG_SCALE_MIN, LOG_SCALE_MAX], "low_pass": float(low_pass)}
    head = json.dumps(header).encode()
    return len(head).to_bytes(4, "little") + head + b"".join(parts)


def write_player(dest: str | Path, block: bytes, title: str) -> Path:
    """The page with `block` (`pack_frames`) gzip'd and base64'd inside, written atomically."""
    from avatarctl.export.player_page import PAGE

    data = base64.b64encode(gzip.compress(block, compresslevel=6, mtime=0)).decode("ascii")
    html = PAGE.replace("__TITLE__", json.dumps(title)[1:-1].replace("<", "")).replace("__DATA__", data)
    with atomic_path(dest) as tmp:
        tmp.write_text(html, encoding="utf-8")
    return Path(dest)
