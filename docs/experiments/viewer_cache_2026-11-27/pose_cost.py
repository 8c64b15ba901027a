"""Posing + encoding cost of the viewer's server per frame (what ViewerController.frame_data does uncached), for the
tree on PYTHONPATH: python pose_cost.py PROJECT [frames]"""
import sys
import time

import torch

from avatarctl.stages.view import ViewConfig, prepare
from avatarctl.viewer.splats import encode_splats

setup = prepare(sys.argv[1], ViewConfig(device="cpu"))
s = setup.session
n = int(sys.argv[2]) if len(sys.argv) > 2 else 24
s.splats(0, "auto")  # warm-up (kernel loads)
pose, enc = [], []
for k in range(1, n + 1):
    f = (k * 5) % len(s.frames)
    t = time.perf_counter()
    sp = s.splats(f, "auto")
    t1 = time.perf_counter()
    encode_splats(sp)
    pose.append(t1 - t)
    enc.append(time.perf_counter() - t1)
    if hasattr(s, "_splats"):
        s._splats.clear()  # trees before 8575e8f cached posed frames in the session: measure uncached posing
ms = sorted(1000 * x for x in pose)
print(f"threads={torch.get_num_threads()} frames={n} posing median {ms[len(ms) // 2]:.1f} ms "
      f"min {ms[0]:.1f} max {ms[-1]:.1f}; encoding median {1000 * sorted(enc)[len(enc) // 2]:.1f} ms")
