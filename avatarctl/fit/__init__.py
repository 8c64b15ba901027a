"""The fit stage: training configuration, lazy data loading and ray sampling, the optimisation loop, checkpoints.

Modules (import the one you need; nothing heavy happens at import time):

- `presets`     the presets, stated once (plain data: `--help` and docs/fit.md are made from it)
- `config`      `FitConfig` (frozen, validated, JSON), `--ablation` and `--set key=value` resolution
- `schedule`    Adam + exponential learning-rate decay (paper: lr 5e-4, decay every 20k iterations)
- `conditioning` per-frame body conditioning (joint transforms, pose features, time stamp t/T)
- `data`        per-frame pose table, a RAM-bounded LRU store of cropped frames, the training ray sampler
- `validate`    held-out-view PSNR (bbox protocol) during training
- `checkpoint`  checkpoint files (plain dicts of tensors / JSON values) and `load_avatar` for render / eval
- `loop`        `fit(project, cfg, ...)`: the training loop (resume, Ctrl-C, logging, stage record)
"""
