#!/bin/bash
# Scratch (not product): second device call: GPU tests + render timing, then a sweep of 5 concurrent GPU fits.
set -u
export PYTHONUNBUFFERED=1
B=${B:-180}
DEV=${DEV:-cuda}
T0=$(date +%s)
el() { echo "[t=$(( $(date +%s) - T0 ))s] $*"; }
W=/tmp/warp_lang-1.19.0-py3-none-manylinux_2_28_x86_64.whl
if [ ! -d /tmp/site/warp ] && [ "$DEV" = cuda ]; then
  cat /tmp/w/wpart.0 /tmp/w/wpart.1 /tmp/w/wpart.2 > $W && \
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site $W || { echo INSTALL FAILED; exit 3; }
fi
[ "$DEV" = cuda ] && export PYTHONPATH=/tmp/site:$PWD
mkdir -p /work/data/syn_small/gt && [ -f /tmp/gt/geometry.npz ] && cp /tmp/gt/geometry.npz /work/data/syn_small/gt/
el pytest
timeout 120 python3 -m pytest -q -m gpu tests/ -p no:cacheprovider 2>&1 | tee $OUT/pytest_gpu.log | tail -6
el suite
timeout 90 python3 -m benchmarks.gpu_suite --out $OUT --device $DEV --parts env,parity,train,render,profile 2>&1 \
  | grep gpu_suite | cut -c1-700
el sweep
fit_eval() {
  n=$1; shift; P=/tmp/S_$n; rm -rf $P; cp -r .gpu/P $P
  OMP_NUM_THREADS=3 timeout $((B + 90)) python3 .gpu/cli.py fit $P --preset gaussians --set time_budget_s=$B \
    --set val_every=0 --set val_pairs=0 "$@" --device $DEV > /tmp/fit_$n.log 2>&1
  OMP_NUM_THREADS=3 timeout 60 python3 .gpu/cli.py eval $P --every 10 --device $DEV > /tmp/eval_$n.log 2>&1
  cp $P/eval/novel_view_bbox/metrics.json $P/eval/metrics_all.json
  OMP_NUM_THREADS=3 timeout 60 python3 .gpu/cli.py eval $P --every 10 --region garment --device $DEV \
    >> /tmp/eval_$n.log 2>&1
  echo "$n done rc=$?"
}
fit_eval control &
fit_eval mask1 --set model.gaussians.lambda_mask=1.0 &
fit_eval img16 --set images_per_batch=16 --set rays_per_batch=16384 &
fit_eval k384 --set model.gaussians.per_node=384 &
fit_eval lrm3 --set model.gaussians.lr_means=4.8e-4 &
wait
el collect
python3 - <<'PY' | tee $OUT/sweep.txt
import json, glob, os
for d in sorted(glob.glob("/tmp/S_*")):
    n = d.split("S_")[1]
    try:
        m = json.load(open(f"{d}/eval/novel_view_bbox/metrics.json"))
        r = m["regions"]; st = json.load(open(f"{d}/project.json"))["stages"]
        fit = [s for s in st if s["stage"] == "fit"][-1]["summary"]
        a = json.load(open(f"{d}/eval/metrics_all.json"))
        print(json.dumps({"name": n, "steps": fit["step"], "all": round(a["psnr"], 3), "garment": round(r["garment"]["psnr"], 3),
                          "flat": round(r["garment"]["flat_colour_psnr"], 3), "body": round(r["body"]["psnr"], 3),
                          "ssim": round(m["ssim"], 4), "mse_train": fit["losses"].get("mse")}))
    except Exception as e:
        print(n, "FAILED", e)
PY
cd /tmp && tar czf $OUT/sweep.tgz S_*/eval S_*/fit/log.jsonl S_*/fit/config.json S_*/project.json fit_*.log eval_*.log
ls -la $OUT
el done
