"""Scratch: one fit + novel-view bbox eval on the frozen-body synth-small project; appends a JSON line to RESULTS."""
import argparse, json, os, shutil, sys, time
sys.path.insert(0, os.getcwd()); sys.path.insert(0, os.path.join(os.getcwd(), ".gpu"))
import frozen
ap = argparse.ArgumentParser()
ap.add_argument("name"); ap.add_argument("--preset", default="cpu"); ap.add_argument("--iters", type=int, default=7000)
ap.add_argument("--set", nargs="*", default=[]); ap.add_argument("--ablation", default=None)
ap.add_argument("--device", default="cuda"); ap.add_argument("--results", required=True)
ap.add_argument("--src", default=".gpu/p_small"); ap.add_argument("--body", default=".gpu/body_small.npz")
ap.add_argument("--work", default="/tmp/runs"); ap.add_argument("--train-frames", default=None)
ap.add_argument("--rtime", action="store_true")
a = ap.parse_args()
frozen.patch(a.body)
from avatarctl.project import Project
from avatarctl.fit.config import resolve_fit_config
from avatarctl.fit.loop import fit
from avatarctl.stages.evaluate import EvalConfig
from avatarctl.stages.evaluate import run as evaluate
dst = os.path.join(a.work, a.name); shutil.rmtree(dst, ignore_errors=True); shutil.copytree(a.src, dst)
if a.train_frames:
    sp = json.load(open(os.path.join(dst, "ingest", "split.json")))
    sp["train_frames"] = [int(x) for x in a.train_frames.split(",")]
    json.dump(sp, open(os.path.join(dst, "ingest", "split.json"), "w"))
cfg = resolve_fit_config(a.preset, ablation=a.ablation, iters=a.iters, overrides=a.set)
t0 = time.time()
res = fit(Project.open(dst), cfg, device=a.device, handle_sigint=False)
tf = time.time() - t0
ev = evaluate(dst, EvalConfig(split="novel_view", protocol="bbox", every=10, sheet_rows=4, device=a.device))
vals = [json.loads(l) for l in open(os.path.join(dst, "fit", "log.jsonl")) if '"val"' in l]
out = dict(name=a.name, preset=a.preset, iters=a.iters, set=a.set, ablation=a.ablation, fit_s=round(tf, 1),
           steps=getattr(res, "step", None), psnr=ev.psnr if hasattr(ev, "psnr") else None,
           ssim=getattr(ev, "ssim", None), val=[(v["step"], round(v["val"]["psnr"], 2)) for v in vals])
print(json.dumps(out), flush=True)
with open(a.results, "a") as f: f.write(json.dumps(out) + "\n")

if a.rtime:
    import torch
    from avatarctl.fit.checkpoint import load_avatar
    from avatarctl.render.engine import render_view
    av = load_avatar(Project.open(dst), a.device)
    cap = av.capture
    st = av.model.node_state(av.conditioning(cap.motion.select(cap.motion.rows_for([0])), True), "mean")
    cam = cap.cameras[cap.split.test_views[0]]
    for f in (1, 2, 2):
        c = cam.scaled(f); ts = []
        with torch.no_grad():
            for _ in range(3):
                if a.device == "cuda": torch.cuda.synchronize()
                t = time.perf_counter(); r = render_view(av.model, st, 0, c, (0.0, 0.0, 0.0), max_rays_per_chunk=65536)
                if a.device == "cuda": torch.cuda.synchronize()
                ts.append(time.perf_counter() - t)
        line = dict(rtime=f"{c.width}x{c.height}", seconds=[round(x, 3) for x in ts], preset=a.preset)
        print(json.dumps(line), flush=True)
        with open(a.results, "a") as fh: fh.write(json.dumps(line) + "\n")
