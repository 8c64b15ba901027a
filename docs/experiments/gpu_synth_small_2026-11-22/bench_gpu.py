"""Scratch: benchmarks/bench.py with 4 real synth-small training poses from the frozen body (no anny needed)."""
import os, sys
sys.path[:0] = [os.getcwd(), os.path.join(os.getcwd(), ".gpu")]
import torch, frozen
fb = frozen.FrozenBody(".gpu/body_small.npz")
import benchmarks.bench as B
def setup(n=4):
    r = torch.arange(n) * 20
    return fb._t, fb.jt[r], fb.pf[r], fb.pv[r]
B.anny_setup = setup
B.main(sys.argv[1:])
