set -u
export PYTHONUNBUFFERED=1 OMP_NUM_THREADS=2
R=$OUT/results.jsonl
run() { n=$1; shift; python3 .gpu/exp.py $n --results $R "$@" > /tmp/$n.log 2>&1; echo "$n rc=$?"; tail -4 /tmp/$n.log; }
run sf_cpu --iters 20000 --train-frames 0 --set time_budget_s=280 &
run sf_paper --preset paper --iters 20000 --train-frames 0 --set time_budget_s=280 val_scale=0.5 &
run paper_full --preset paper --iters 20000 --rtime --set time_budget_s=400 val_scale=0.5 &
wait
cd /tmp/runs && tar czf $OUT/runs.tgz */fit/log.jsonl */eval/*/sheet.png */eval/*/metrics.json /tmp/*.log 2>/dev/null
