#!/bin/bash
# one tiny (demo capture) run: fresh copy of P_tiny, fit N steps with the gaussians preset, eval novel view + novel pose
n=$1; iters=$2; shift 2
P=${OUT:-tn}/$n
rm -rf $P; mkdir -p $P; cp -r ${SRC:-P_tiny}/ingest ${SRC:-P_tiny}/project.json $P/

s=$(date +%s.%N)
OMP_NUM_THREADS=${T:-1} avatarctl fit $P --preset ${PRESET:-gaussians} --iters $iters --set rays_per_batch=1024 --set val_every=0 --set val_pairs=0 "$@" > $P.fit.log 2>&1
e=$(date +%s.%N)
OMP_NUM_THREADS=${T:-1} avatarctl eval $P --every 2 > $P.eval.log 2>&1
OMP_NUM_THREADS=${T:-1} avatarctl eval $P --every 2 --region garment --name nv_garment > $P.evalg.log 2>&1
OMP_NUM_THREADS=${T:-1} avatarctl eval $P --every 2 --split novel_pose > $P.evalnp.log 2>&1
python3 - <<PY
import json
m=json.load(open('$P/eval/novel_view_bbox/metrics.json'))
r=json.load(open('$P/eval/nv_garment/metrics.json')).get('regions',{})
g=r.get('garment',{}); b=r.get('body',{})
n=json.load(open('$P/eval/novel_pose_bbox/metrics.json'))
line=f"$n iters=$iters fit_s={$e-$s:.0f} NV {m['psnr']:.2f}/{m['ssim']:.3f} garment {g.get('psnr',0):.2f} (flat {g.get('flat_colour_psnr',0):.2f}) body {b.get('psnr',0):.2f} NP {n['psnr']:.2f}/{n['ssim']:.3f} args: $*"
print(line); open('${OUT:-tn}/results.txt','a').write(line+'\n')
PY
