"""Side-by-side scores of several projects (e.g. the full model vs its ablations), from their latest metrics.json.

For each project the latest `eval` record of the manifest with the requested split and protocol is used (when no
split/protocol is given, those of the first project's latest eval). Nothing is rendered. Rows whose evaluated
(frame, view) images differ from the first project's are flagged: their numbers are not directly comparable.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from avatarctl.errors import ProjectError
from avatarctl.evaluate.report import EvalMetrics
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
                   ) -> tuple[Path, EvalMetrics]:
    """(path, contents) of the latest metrics.json of `project` matching split / protocol (None = any)."""
    for rec in reversed(project.manifest.stages):
        if rec.stage != "eval":
            continue
        if split is not None and rec.config["split"] != split:
            continue
        if protocol is not None and rec.config["protocol"] != protocol:
            continue
        for out in rec.outputs:
            path = project.root / out / "metrics.json"
            if path.is_file():
                return path, _read(path)
    want = " ".join(x for x in (f"--split {split}" if split else "", f"--protocol {protocol}" if protocol else "") if x)
    raise ProjectError(f"no eval results{' for ' + want if want else ''}", where=str(project.root),
                       fix=f"run `avatarctl eval {project.root}{' ' + want if want else ''}` first")


def _read(path: Path) -> EvalMetrics:
    try:
        return EvalMetrics.from_json(json.loads(path.read_text()))
    except (KeyError, TypeError, ValueError) as e:
        raise ProjectError(f"malformed metrics.json ({type(e).__name__}: {e})", where=str(path),
                           fix="re-run `avatarctl eval` on this project") from None


def compare(projects: list[str | Path], split: str | None = None, protocol: str | None = None) -> list[ComparisonRow]:
    """One row per project (in the given order), all on the same split and protocol."""
    rows: list[ComparisonRow] = []
    ref_pairs: set[tuple[int, str]] | None = None
    for p in projects:
        proj = Project.open(p)
        path, m = latest_metrics(proj, split, protocol)
        split, protocol = m.split, m.protocol  # the first project fixes them for the rest
        pairs = m.pairs
        if ref_pairs is None:
            ref_pairs = pairs
        rows.append(ComparisonRow(project=str(proj.root), label=m.model.label, eval_name=path.parent.name,
                                  split=split, protocol=protocol, psnr=float(m.psnr), ssim=float(m.ssim),
                                  lpips=m.lpips, images=m.images, checkpoint_step=m.checkpoint_step,
                                  same_images=pairs == ref_pairs, metrics_path=path))
    return rows
