"""Per-frame Delta n of a fitted project's training frames: RMS over frames of the node translation, hull vs body nodes."""
import sys
import torch
from avatarctl.project import Project
from avatarctl.fit.checkpoint import load_avatar

for p in sys.argv[1:]:
    a = load_avatar(Project.open(p))
    m = a.model
    cond = a.conditioning(a.capture.motion.select(a.train_frames), True)
    with torch.no_grad():
        st = m.node_state(cond, "mean")
    dn = st.delta_n  # [T, N, 3]
    mean = dn.mean(0, keepdim=True)
    var = (dn - mean).norm(dim=-1)  # per-frame deviation from the node's mean offset
    print(p, "frames", dn.shape[0], "|dn| mean %.4f m, max %.4f; frame-to-frame spread RMS %.4f m, max %.4f" % (
        dn.norm(dim=-1).mean(), dn.norm(dim=-1).max(), var.pow(2).mean().sqrt(), var.max()))
    # hull nodes are the last ones, if any
    nh = getattr(m.cfg.hull, 'nodes', 0)
    print("  hull cfg", m.cfg.hull)
