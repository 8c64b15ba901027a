#!/usr/bin/env bash
# The run behind report.md / report.csv (2026-11-25, 2-core CPU shared with other jobs, no GPU):
# synth tiny / tight / monocular (seed 0), 7 models x 2 fit seeds, fit preset cpu, 300 steps each.
set -euo pipefail
OUT=${1:-/work/data/wt31/reproduce_300}
nice -n 5 env OMP_NUM_THREADS=1 avatarctl reproduce "$OUT" --budget-steps 300 --seeds 2 --device cpu
# The committed sheets are OUT/sheets/*.png palette-quantised to 64 colours (size only; same pixels' layout):
#   python -c "import sys; from PIL import Image; [Image.open(p).convert('RGB').quantize(64).save(p, optimize=True) for p in sys.argv[1:]]" sheets/*.png
