#!/bin/bash
# usage: run.sh NAME SRC_PROJECT STEPS [fit args...]   (1 thread; then eval novel_view --every 20 --region garment)
name=$1; src=$2; secs=$3; shift 3
d=${RUNS:-/tmp/runs}/$name  # RUNS: where the runs go; SRC_PROJECT must be an absolute path
rm -rf $d; mkdir -p $d
cp -r $src/ingest $src/project.json $d/
cd "$(dirname "$0")/../../.." && . .venv/bin/activate  # the repository root
export OMP_NUM_THREADS=1
avatarctl fit $d --iters $secs --set val_every=0 --set val_pairs=0 "$@" > $d.fit.out 2>&1
avatarctl eval $d --every 20 --region garment --save-images > $d.eval.out 2>&1
python - <<PY
import json
m=json.load(open("$d/eval/novel_view_bbox/metrics.json"))
r=m["regions"]; recs=[json.loads(l) for l in open("$d/fit/log.jsonl")]
steps=[x for x in recs if "step" in x][-1]["step"]
import csv
box=[float(x["psnr"]) for x in csv.DictReader(open("$d/eval/novel_view_bbox/per_frame.csv"))]
print("$name", "steps", steps, "box %.2f / SSIM %.4f"%(sum(box)/len(box), m["ssim"]), "garment %.2f"%r["garment"]["psnr"], "body %.2f"%r["body"]["psnr"], "garment share err %.2f"%r["garment"]["share_of_error"])
PY
