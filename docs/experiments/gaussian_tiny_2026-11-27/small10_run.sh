#!/bin/bash
# a 10-minute synth-small run: fit then held-out views by region (every 10) and novel poses (every 5)
n=$1; shift
OMP_NUM_THREADS=1 avatarctl fit $n --preset gaussians --set time_budget_s=600 --set val_every=0 --set val_pairs=0 "$@" > $n.fit.log 2>&1
OMP_NUM_THREADS=1 avatarctl eval $n --every 10 --region garment > $n.eval.log 2>&1
cp $n/eval/novel_view_bbox/metrics.json $n/eval/nv_garment.json
OMP_NUM_THREADS=1 avatarctl eval $n --every 10 > $n.eval2.log 2>&1
OMP_NUM_THREADS=1 avatarctl eval $n --split novel_pose --every 5 > $n.eval3.log 2>&1
python3 -c "
import json;g=json.load(open('$n/eval/nv_garment.json'));r=g['regions']
a=json.load(open('$n/eval/novel_view_bbox/metrics.json'));p=json.load(open('$n/eval/novel_pose_bbox/metrics.json'))
st=json.load(open('$n/project.json'))['stages']; f=[s for s in st if s['stage']=='fit'][-1]['summary']
print('$n', 'steps', f['step'], 'all', round(a['psnr'],2), round(a['ssim'],4), 'garment', round(r['garment']['psnr'],2), 'flat', round(r['garment']['flat_colour_psnr'],2), 'body', round(r['body']['psnr'],2), 'novel_pose', round(p['psnr'],2), round(p['ssim'],4))"
