#!/bin/bash
# One run of docs/experiments/hull_auto_2026-11-25 (1,500 steps, 1 thread, cpu preset, then eval).
# usage: run.sh NAME SRC_PROJECT KIND [fit args...]
#   KIND small: eval --every 20 --region garment (novel view, with --save-images) and --split novel_pose
#   KIND tight: eval --every 4 (novel view, with --save-images) and --split novel_pose
#   SRC_PROJECT: an absolute path (copied: its ingest/ and project.json); RUNS: where the runs go (/tmp/runs)
here=$(cd "$(dirname "$0")" && pwd)
name=$1; src=$2; kind=$3; shift 3
d=${RUNS:-/tmp/runs}/$name
rm -rf $d; mkdir -p $d
cp -r $src/ingest $src/project.json $d/
cd "$here/../../.." && . .venv/bin/activate  # the repository root
export OMP_NUM_THREADS=1
avatarctl fit $d --iters 1500 --set val_every=0 --set val_pairs=0 "$@" > $d.fit.out 2>&1
if [ "$kind" = small ]; then
  avatarctl eval $d --every 20 --region garment --save-images > $d.eval.out 2>&1
  avatarctl eval $d --every 20 --region garment --split novel_pose > $d.evalp.out 2>&1
else
  avatarctl eval $d --every 4 --save-images > $d.eval.out 2>&1
  avatarctl eval $d --every 4 --split novel_pose > $d.evalp.out 2>&1
fi
python "$here/score.py" $d $name
