"""Side-by-side scores of several projects (e.g. the full model vs its ablations), from their latest metrics.json.

For each project the latest `eval` record of the manifest with the requested split and protocol is used (when no
split/protocol is given, those of the first project's latest eval). Nothing is rendered. Rows whose evaluated
(frame, view) images differ from the first project's are flagged: their numbers are not directly comparable.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from avatarctl.errors import ProjectError
from avatarctl.project import Project


@dataclass(frozen=True)
class ComparisonRow:
    project: str  # project directory
    label: str  # what distinguishes it: fit ablations / variant, else "full model"
    eval_name: str
    split: str
    protocol: str
    psnr: float
    ssim: float
    lpips: float | None
    images: int
    checkpoint_step: int
    same_images: bool  # evaluated the same (frame, view) pairs as the first row
    metrics_path: Path


def latest_metrics(project: Project, split: str | None = None, protocol: str | None = None
                   ) -> tuple[Path, dict[str, Any]]:
    """(path, contents) of the latest metrics.json of `project` matching split / protocol (None = any)."""
    for rec in reversed(project.manifest.stages):
        if rec.stage != "eval":
            continue
        cfg = rec.config or {}
        if split is not None and cfg.get("split") != split:
            continue
        if protocol is not None and cfg.get("protocol") != protocol:
            continue
        for out in rec.outputs:
            path = project.root / out / "metrics.json"
            if path.is_file():
                return path, json.loads(path.read_text())
    want = " ".join(x for x in (f"--split {split}" if split else "", f"--protocol {protocol}" if protocol else "") if x)
    raise ProjectError(f"no eval results{' for ' + want if want else ''}", where=str(project.root),
                       fix=f"run `avatarctl eval {project.root}{' ' + want if want else ''}` first")


def _label(metrics: dict[str, Any]) -> str:
    model = metrics.get("model") or {}
    parts = list(model.get("ablations") or [])
    if not parts:
        if model.get("variant", "slrf") != "slrf":
            parts.append(str(model["variant"]))
        if model.get("use_delta_n") is False:
            parts.append("no-delta-n")
        if model.get("use_embedding") is False:
            parts.append("no-embedding")
        if model.get("latent", "cvae") != "cvae":
            parts.append(f"latent={model['latent']}")
    return ", ".join(parts) if parts else "full model"


def compare(projects: list[str | Path], split: str | None = None, protocol: str | None = None) -> list[ComparisonRow]:
    """One row per project (in the given order), all on the same split and protocol."""
    rows: list[ComparisonRow] = []
    ref_pairs: set[tuple[int, str]] | None = None
    for p in projects:
        proj = Project.open(p)
        path, m = latest_metrics(proj, split, protocol)
        split, protocol = m["split"], m["protocol"]  # the first project fixes them for the rest
        pairs = {(int(f), str(v)) for f in m.get("frames", []) for v in m.get("views", [])}
        if ref_pairs is None:
            ref_pairs = pairs
        rows.append(ComparisonRow(project=str(proj.root), label=_label(m), eval_name=path.parent.name, split=split,
                                  protocol=protocol, psnr=float(m["psnr"]), ssim=float(m["ssim"]),
                                  lpips=m.get("lpips"), images=int(m.get("images", len(pairs))),
                                  checkpoint_step=int(m.get("checkpoint_step", -1)), same_images=pairs == ref_pairs,
                                  metrics_path=path))
    return rows
