set -u
export PYTHONUNBUFFERED=1 OMP_NUM_THREADS=2
R=$OUT/results.jsonl; B=330
run() { n=$1; shift; python3 .gpu/exp.py $n --results $R "$@" > /tmp/$n.log 2>&1; echo "$n rc=$?"; tail -1 /tmp/$n.log; }
run sum_cpu --iters 7000 --set time_budget_s=$B &
run sum_abl --iters 7000 --ablation no-delta-n,no-embedding --set time_budget_s=$B &
run sum_paper --preset paper --iters 7000 --set time_budget_s=$B val_scale=0.5 &
run sum_wide --iters 7000 --set time_budget_s=$B model.node_width=64 model.feature_dim=64 &
run sum_pf --iters 7000 --ablation per-frame-latent --set time_budget_s=$B &
run sum_det --iters 7000 --ablation deterministic --set time_budget_s=$B &
run mean_cpu --iters 7000 --set time_budget_s=$B model.rec_reduction=mean &
wait
python3 .gpu/bench_gpu.py --device cuda --repeats 5 --steps 20 --rays-throughput 2048 --out $OUT/bench_gpu.json 2>&1 | tail -12
cd /tmp/runs && tar czf $OUT/runs.tgz */fit/log.jsonl */eval/*/sheet.png */eval/*/metrics.json /tmp/*.log 2>/dev/null
