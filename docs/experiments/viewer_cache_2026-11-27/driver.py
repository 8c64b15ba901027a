"""benchmarks.viewer_page.main, unchanged, plus what the controller's FrameCache held at the end (issue 29 re-measure).

    PYTHONPATH=<tree> OMP_NUM_THREADS=1 [I29_CACHE_FRAMES=32 I29_CACHE_MIB=192] python driver.py STATS.json <viewer_page args>

I29_POSES=FILE: the viewer shows this motion file (as `avatarctl view --poses FILE`) instead of the project's frames
(benchmarks.viewer_page has no such option), by wrapping stages.view.prepare here.
I29_CACHE_FRAMES / I29_CACHE_MIB: the controller's FrameCache limits for this run (default: the product's, 512 / 384;
32 / 192 were the limits before 8575e8f), set by wrapping ViewerController.__init__ here (no product change).
Also records each playback window (set_playing True -> False) and the frames the server pushed per second in
consecutive 8 s slices of it (120 frames at 15 fps: one loop of the project's motion per slice).
"""
import collections
import json
import os
import sys
import time
from pathlib import Path

import benchmarks.viewer_page as vp

from avatarctl.viewer import controller as ctl

captured = {"plays": []}
_start = vp.start_viewer
if os.environ.get("I29_CACHE_FRAMES"):
    _init = ctl.ViewerController.__init__

    def init(self, *a, **k):
        k["cache_frames"] = int(os.environ["I29_CACHE_FRAMES"])
        k["cache_bytes"] = int(float(os.environ.get("I29_CACHE_MIB", "384")) * 2 ** 20)
        _init(self, *a, **k)

    ctl.ViewerController.__init__ = init
if os.environ.get("I29_POSES"):  # the benchmark plays the project's motion only: show this motion file instead
    import dataclasses

    from avatarctl.stages import view as view_stage

    _prepare = view_stage.prepare

    def prepare(project, cfg):
        return _prepare(project, dataclasses.replace(cfg, poses=(os.environ["I29_POSES"],)))

    view_stage.prepare = prepare


def start(*a, **k):
    captured["server"] = s = _start(*a, **k)
    c = s.controller
    _set_playing = c.set_playing

    def set_playing(on):
        if on:
            captured["plays"].append([time.monotonic(), None])
        elif captured["plays"] and captured["plays"][-1][1] is None:
            captured["plays"][-1][1] = time.monotonic()
        _set_playing(on)

    c.set_playing = set_playing
    return s


vp.start_viewer = start
stats_path = Path(sys.argv[1])
load0 = os.getloadavg()
vp.main(sys.argv[2:])
c = captured["server"].controller
counts = collections.Counter(k for _, k in c.posed)
stats = {"motion_frames": len(c.state.labels), "motion_fps": c.state.fps,
         "cache_frames": len(c.cache), "cache_mib": round(c.cache.nbytes / 2 ** 20, 1),
         "cache_limits": [c.cache.max_frames, round(c.cache.max_bytes / 2 ** 20)],
         "posings": len(c.posed), "distinct_frames_posed": len(counts),
         "frames_posed_more_than_once": sum(1 for v in counts.values() if v > 1),
         "pose_seconds_mean": round(c.pose_seconds, 4),
         "rss_mb_end": round(vp.rss_mb(), 1), "peak_rss_mb": round(vp.peak_rss_mb(), 1),
         "load_start": load0, "load_end": os.getloadavg(), "playback_slices": []}
pushes = [t for t, _ in captured["server"].pushes]
for t0, t1 in captured["plays"]:
    row, a = [], t0
    while a < t1 - 0.5:
        b = min(a + 8.0, t1)
        n = sum(1 for t in pushes if a <= t < b)
        row.append(round(n / (b - a), 2))
        a = b
    stats["playback_slices"].append(row)
print(json.dumps(stats))
stats_path.write_text(json.dumps(stats, indent=1) + "\n")
