"""One line of figures for a run of run.sh: steps, novel-view and novel-pose box PSNR (the mean of the per-image
PSNRs of per_frame.csv) / SSIM, the garment and body regions when scored, and the fit log's hull line.

    python score.py RUN NAME
"""

from __future__ import annotations

import csv
import json
import sys


def main(run: str, name: str) -> None:
    log = [json.loads(line) for line in open(f"{run}/fit/log.jsonl")]
    out = [name, f"steps {[r for r in log if 'step' in r][-1]['step']}"]
    for split in ("novel_view", "novel_pose"):
        try:
            m = json.load(open(f"{run}/eval/{split}_bbox/metrics.json"))
        except FileNotFoundError:
            continue
        box = [float(r["psnr"]) for r in csv.DictReader(open(f"{run}/eval/{split}_bbox/per_frame.csv"))]
        s = f"{split} box {sum(box) / len(box):.2f} / SSIM {m['ssim']:.4f}"
        for region, r in (m.get("regions") or {}).items():  # tight clothing: no garment (psnr None)
            if r and r.get("psnr") is not None:
                s += f" {region} {r['psnr']:.2f}"
        out.append(s)
    out += [r["note"] for r in log if r.get("note", "").startswith("hull")]
    print(" | ".join(out))


if __name__ == "__main__":
    main(*sys.argv[1:3])
