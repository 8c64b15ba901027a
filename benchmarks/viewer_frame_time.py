"""Frame time of the web viewer's render callback (`avatarctl view`), without a browser.

Loads the avatar the way `avatarctl view` does (`stages.view.prepare`), points the viewer camera from the first
held-out camera at the subject (square image, the camera's vertical field of view, as the page starts), and times
`ViewerSession.render` at each resolution: the full-quality image and the preview (a quarter of the side) shown
while the camera moves. Wall time and process CPU time are both reported (on a shared machine the wall time
depends on the load; with one torch thread the CPU time is what an idle core would take). The first call per
(frame, latent) also builds the node state; it is reported apart.

    python -m benchmarks.viewer_frame_time PROJECT [--resolutions 256 512] [--repeats 3] [--device cpu] [--out F]
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np


@dataclass(frozen=True)
class FrameTime:
    resolution: int  # the requested side, pixels
    kind: str  # "full" or "preview"
    side: int  # the rendered side: the resolution, or a quarter of it for the preview
    median_s: float
    min_s: float
    median_cpu_s: float  # process CPU time
    repeats: int


@dataclass(frozen=True)
class ViewerFrameTimes:
    project: str
    device: str
    torch_threads: int
    node_state_s: float  # the first call of a (frame, latent): the node state, cached afterwards
    fov_y_rad: float
    rows: tuple[FrameTime, ...]  # full and preview per resolution


def main(argv: list[str] | None = None) -> ViewerFrameTimes:
    import torch

    from avatarctl.export.skinning import matrix_to_quaternion
    from avatarctl.geometry.cameras import look_at
    from avatarctl.stages.view import ViewConfig, prepare
    from avatarctl.viewer.progressive import ViewRequest

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("project", type=Path)
    ap.add_argument("--resolutions", type=int, nargs="+", default=[256, 512])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", type=Path, default=None, help="write the results as JSON here")
    args = ap.parse_args(argv)

    setup = prepare(args.project, ViewConfig(device=args.device))
    fov_y = setup.initial.fov_y
    R, _ = look_at(np.asarray(setup.initial.position), np.asarray(setup.initial.look_at), np.asarray(setup.initial.up))
    x, y, z, w = matrix_to_quaternion(R.T)
    base = ViewRequest(wxyz=(w, x, y, z), position=setup.initial.position, fov_y=fov_y, aspect=1.0, frame=0,
                       latent="auto", resolution=64)
    t0 = time.perf_counter()
    setup.session.state(0, "auto")
    state_s = time.perf_counter() - t0
    rows = []
    for res in args.resolutions:
        for kind, side in (("full", res), ("preview", max(16, res // 4))):
            req = replace(base, resolution=side)
            times, cpu = [], []
            for _ in range(args.repeats):
                t0, c0 = time.perf_counter(), time.process_time()
                setup.session.render(req)
                times.append(time.perf_counter() - t0)
                cpu.append(time.process_time() - c0)
            rows.append(FrameTime(resolution=res, kind=kind, side=side, median_s=float(np.median(times)),
                                  min_s=float(np.min(times)), median_cpu_s=float(np.median(cpu)),
                                  repeats=args.repeats))
            print(f"{res}^2 {kind:7s} ({side}^2): wall median {np.median(times):.3f} s (min {np.min(times):.3f}), "
                  f"process CPU {np.median(cpu):.3f} s", flush=True)
    out = ViewerFrameTimes(project=str(args.project), device=str(setup.avatar.device),
                           torch_threads=torch.get_num_threads(), node_state_s=state_s, fov_y_rad=fov_y,
                           rows=tuple(rows))
    print(f"node state of a frame: {state_s:.3f} s (once per frame and latent, cached)")
    if args.out:
        args.out.write_text(json.dumps(asdict(out), indent=2))
    return out


if __name__ == "__main__":
    main()
