#!/bin/bash
# One run of docs/experiments/pose_smooth_2026-11-25: fit (1 thread, cpu preset, paper node placement so the runs
# compare with docs/fit.md's earlier pose-refinement rows), eval on held-out views with the garment / body split.
# usage: run.sh NAME SRC_PROJECT STEPS [fit args...]     (RUNS: where the runs go, default /tmp/runs)
here=$(cd "$(dirname "$0")" && pwd)
name=$1; src=$2; steps=$3; shift 3
d=${RUNS:-/tmp/runs}/$name
rm -rf $d; mkdir -p $d
cp -r $src/ingest $src/project.json $d/
cd "$here/../../.." && . .venv/bin/activate  # the repository root
export OMP_NUM_THREADS=1
avatarctl fit $d --iters $steps --set val_every=0 --set val_pairs=0 --set model.hull_nodes=0 "$@" > $d.fit.out 2>&1
avatarctl eval $d --every 20 --region garment --save-images > $d.eval.out 2>&1
python "$here/../hull_auto_2026-11-25/score.py" $d $name
