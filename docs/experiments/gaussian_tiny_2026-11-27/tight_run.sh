#!/bin/bash
# a 10-minute tight run: fit then novel poses (every 5) and held-out views (every 10)
n=$1; shift
OMP_NUM_THREADS=1 avatarctl fit $n --preset gaussians --set time_budget_s=600 --set val_every=0 --set val_pairs=0 "$@" > $n.fit.log 2>&1
OMP_NUM_THREADS=1 avatarctl eval $n --split novel_pose --every 5 > $n.eval.log 2>&1
OMP_NUM_THREADS=1 avatarctl eval $n --every 10 > $n.eval2.log 2>&1
python3 -c "
import json
a=json.load(open('$n/eval/novel_view_bbox/metrics.json'));p=json.load(open('$n/eval/novel_pose_bbox/metrics.json'))
st=json.load(open('$n/project.json'))['stages']; f=[s for s in st if s['stage']=='fit'][-1]['summary']
print('$n', 'steps', f['step'], 'novel_pose', round(p['psnr'],2), round(p['ssim'],4), 'novel_view', round(a['psnr'],2), round(a['ssim'],4))"
