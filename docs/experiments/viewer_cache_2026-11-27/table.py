"""Rows of the figures of a viewer_page JSON (one or several rounds)."""
import json
import sys

for path in sys.argv[1:]:
    d = json.load(open(path))
    rounds = d["viewer"] if isinstance(d, dict) and "viewer" in d else [d]
    for i, r in enumerate(rounds):
        o = r["orbit"]
        fc = r["frame_change_ms"]
        full = r["frame_change_full_ms"]
        print(f"{path.split('/')[-1]} r{i + 1} budget={'on' if r['budget'] else 'off'} load={r['load_average']} "
              f"orbit_load={o['load_average']} | orbit {o['fps']} fps drawn {o['drawn_fps']} cpu/frame "
              f"{o['cpu_ms_per_frame']} ms change {o['image_change']} | frame change {min(fc):.0f}-{max(fc):.0f} ms "
              f"(median {sorted(fc)[len(fc) // 2]:.0f}, n={len(fc)}) full {min(full):.0f}-{max(full):.0f} | "
              f"playback {r['playback_fps_page']} img/s pushes {r['playback_pushes_per_s']} | peak RSS "
              f"{r['peak_rss_mb']} MB | pose {r['splat_seconds'] * 1000:.0f} ms enc {r['encode_seconds'] * 1000:.1f} ms"
              f" | psnr {r['preview_psnr_db']} idle {r['idle_changes_per_s']} 2nd tab {r['second_tab_drawn']}")
