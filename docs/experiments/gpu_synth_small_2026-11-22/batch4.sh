set -u
export PYTHONUNBUFFERED=1 OMP_NUM_THREADS=2
python3 -m pytest -q -p no:cacheprovider tests/test_gpu_parity.py 2>&1 | grep -E "^E |Error|passed|failed" | head -20
R=$OUT/results.jsonl
python3 .gpu/exp.py amp_cpu --iters 20000 --set time_budget_s=40 amp=true val_every=0 --results $R > /tmp/a.log 2>&1 &
python3 .gpu/exp.py fp32_cpu --iters 20000 --set time_budget_s=40 val_every=0 --results $R > /tmp/b.log 2>&1 &
wait; tail -n 2 /tmp/a.log; tail -n 2 /tmp/b.log
