#!/bin/bash
# One run of docs/experiments/garment_latent_2026-11-26 (synth small, 1 thread, cpu preset): fit, then
# eval --every 20 --region garment (novel view, with --save-images) and --split novel_pose, then one score line.
# usage: run.sh NAME SRC_PROJECT [fit args...]
#   SRC_PROJECT: an absolute path (its ingest/ and project.json are copied); RUNS: where runs go (/tmp/runs)
#   ITERS: fit steps (1500); AVATARCTL: the command to run (default avatarctl; oracle.py wraps it, see README)
here=$(cd "$(dirname "$0")" && pwd)
name=$1; src=$2; shift 2
d=${RUNS:-/tmp/runs}/$name
rm -rf $d; mkdir -p $d
cp -r $src/ingest $src/project.json $d/
cd "$here/../../.." && . .venv/bin/activate  # the repository root
export OMP_NUM_THREADS=1
cmd=${AVATARCTL:-avatarctl}
start=$(date +%s)
$cmd fit $d --iters ${ITERS:-1500} --set val_every=0 --set val_pairs=0 "$@" > $d.fit.out 2>&1
echo "fit wall $(( $(date +%s) - start )) s" > $d.time
$cmd eval $d --every 20 --region garment --save-images > $d.eval.out 2>&1
$cmd eval $d --every 20 --region garment --split novel_pose > $d.evalp.out 2>&1
python "$here/../hull_auto_2026-11-25/score.py" $d $name | tee $d.score
