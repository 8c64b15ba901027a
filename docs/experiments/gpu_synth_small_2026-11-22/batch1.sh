set -u
export PYTHONUNBUFFERED=1 OMP_NUM_THREADS=2
nvidia-smi --query-gpu=name,memory.total --format=csv
R=$OUT/results.jsonl; B=360
run() { n=$1; shift; python3 .gpu/exp.py $n --results $R "$@" > /tmp/$n.log 2>&1; echo "$n rc=$?"; tail -2 /tmp/$n.log; }
run base --iters 7000 --set time_budget_s=$B &
run sched --iters 7000 --set time_budget_s=$B lr_decay_every=2100 &
run wide --iters 7000 --set time_budget_s=$B lr_decay_every=2100 model.node_width=64 model.feature_dim=64 &
run long --iters 21000 --set time_budget_s=$B lr_decay_every=6300 &
run paper --preset paper --iters 7000 --set time_budget_s=$B lr_decay_every=2100 val_scale=0.5 &
run r2048 --iters 7000 --set time_budget_s=$B lr_decay_every=2100 rays_per_batch=2048 &
run abl --iters 7000 --ablation no-delta-n,no-embedding --set time_budget_s=$B lr_decay_every=2100 &
wait
cd /tmp/runs && tar czf $OUT/runs.tgz */fit/log.jsonl */eval/*/sheet.png */eval/*/metrics.json /tmp/*.log 2>/dev/null
cat $R
