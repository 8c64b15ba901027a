#!/bin/bash
# Scratch (not product): one device call = the GPU checks of issue 28 + a GPU fit of synth small (frozen body).
set -u
export PYTHONUNBUFFERED=1
B=${B:-270}
DEV=${DEV:-cuda}
T0=$(date +%s)
el() { echo "[t=$(( $(date +%s) - T0 ))s] $*"; }
W=/tmp/warp_lang-1.19.0-py3-none-manylinux_2_28_x86_64.whl
ls -la /tmp/w; du -sh .gpu
if [ ! -d /tmp/site/warp ]; then
  cat /tmp/w/wpart.0 /tmp/w/wpart.1 /tmp/w/wpart.2 > $W && \
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site $W || { echo INSTALL FAILED; exit 3; }
fi
export PYTHONPATH=/tmp/site:$PWD
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv
el pytest
timeout 240 python3 -m pytest -q -m gpu tests/ -p no:cacheprovider 2>&1 | tee $OUT/pytest_gpu.log | tail -15
el suite
timeout 150 python3 -m benchmarks.gpu_suite --out $OUT --device $DEV 2>&1 | cut -c1-400
el fit
P=/tmp/P; rm -rf $P; cp -r .gpu/P $P
timeout $((B + 120)) python3 .gpu/cli.py fit $P --preset gaussians --set time_budget_s=$B --set val_every=0 \
  --set val_pairs=0 --device $DEV > /tmp/fit.log 2>&1; echo "fit rc=$?"; tail -32 /tmp/fit.log | cut -c1-200
el eval
timeout 90 python3 .gpu/cli.py eval $P --every 10 --device $DEV > /tmp/eval.log 2>&1; echo "eval rc=$?"
grep -i "psnr\|ssim\|error\|time" /tmp/eval.log | head -12
tar czf $OUT/results.tgz -C $P project.json fit/log.jsonl fit/config.json eval /tmp/fit.log /tmp/eval.log
[ -f $P/fit/checkpoints/latest.pt ] && split -b 15M $P/fit/checkpoints/latest.pt $OUT/ckpt_
ls -la $OUT
el done
