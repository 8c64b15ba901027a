"""The reproduction report of `avatarctl reproduce`: the paper's figures beside ours, one row per claim.

A `ReportRow` holds one quantity (a model's score, or the difference the paper's claim is about) measured over fit
seeds (`Measurement`: per-seed values, mean, half range), the paper's figure as printed, the protocol, the budget
and a verdict. Verdicts compare the *sign* of a difference with the paper's (our synthetic captures, sizes and
budgets are not the paper's, so absolute dB are not expected to match):

- `agrees`: every seed's difference has the paper's sign, and the mean is larger than the half range over seeds
  and than `MIN_EFFECT_DB`;
- `disagrees`: the same with the opposite sign;
- `inconclusive`: otherwise (the seeds disagree with each other, a difference under `MIN_EFFECT_DB` or within the
  seed spread, or one seed and a difference under 1 dB);
- `no paper number`: the paper shows the setting only qualitatively.

Paper numbers are from `slrf_paper.tex` (tables in caption order; the supplement restarts at Tab. A, which is
the hyper-parameter table: the node-variable knock-out is supp. Tab. B, the cVAE ablation supp. Tab. C).
"""

from __future__ import annotations

import csv
import io
from dataclasses import dataclass

VERDICTS = ("agrees", "disagrees", "inconclusive", "no paper number", "")
MIN_EFFECT_DB = 0.1  # a mean difference smaller than this is inconclusive whatever the seeds say


@dataclass(frozen=True)
class PaperFigure:
    """A number (or numbers) the paper prints, and the sign of the difference it claims."""

    where: str  # "Tab. 1", "supp. Tab. B", "supp. Sec. C.2", ...
    text: str  # as printed, e.g. "23.43 / 22.19 dB (Dress1 / Dress2)"
    claim_sign: int = 0  # +1: the difference is positive in the paper; 0: no number / not a difference


# The paper's figures the reproduction compares against (slrf_paper.tex).
PAPER = {
    "tab1_full": PaperFigure("Tab. 1", "23.43 / 22.19 dB, SSIM 0.891 / 0.900 (Dress1 / Dress2)"),
    "tab1_baseline": PaperFigure("Tab. 1", "19.52 / 20.49 dB, SSIM 0.848 / 0.877 (Animatable NeRF)"),
    "tab1_diff": PaperFigure("Tab. 1", "+3.91 / +1.70 dB", +1),
    "tab2_seen_full": PaperFigure("Tab. 2", "28.32 / 30.79 dB (387 / 392, seen poses)"),
    "tab2_seen_baseline": PaperFigure("Tab. 2", "24.38 / 27.43 dB (Animatable NeRF, seen)"),
    "tab2_seen_diff": PaperFigure("Tab. 2", "+3.94 / +3.36 dB", +1),
    "tab2_unseen_full": PaperFigure("Tab. 2", "23.61 / 26.74 dB (387 / 392, unseen poses)"),
    "tab2_unseen_baseline": PaperFigure("Tab. 2", "21.29 / 24.59 dB (Animatable NeRF, unseen)"),
    "tab2_unseen_diff": PaperFigure("Tab. 2", "+2.32 / +2.15 dB", +1),
    "mono": PaperFigure("Fig. 6", "qualitative only (PeopleSnapshot)"),
    "tabB_full": PaperFigure("supp. Tab. B", "21.48 dB (full)"),
    "tabB_no_e": PaperFigure("supp. Tab. B", "20.47 dB (w/o e)"),
    "tabB_no_dn_e": PaperFigure("supp. Tab. B", "17.52 dB (w/o Δn, e)"),
    "tabB_diff_e": PaperFigure("supp. Tab. B", "+1.01 dB", +1),
    "tabB_diff_dn_e": PaperFigure("supp. Tab. B", "+3.96 dB", +1),
    "tabC_cvae": PaperFigure("supp. Tab. C", "25.62 dB (cVAE)"),
    "tabC_det": PaperFigure("supp. Tab. C", "25.34 dB (deterministic)"),
    "tabC_diff": PaperFigure("supp. Tab. C", "+0.28 dB", +1),
    "sparse_speed": PaperFigure("supp. Sec. C.2", "4x faster", +1),
    "sparse_memory": PaperFigure("supp. Sec. C.2", "-85 % memory", +1),
}


@dataclass(frozen=True)
class Measurement:
    """One quantity over seeds (or one run)."""

    values: tuple[float, ...]
    unit: str = "dB"

    @property
    def n(self) -> int:
        return len(self.values)

    @property
    def mean(self) -> float:
        return sum(self.values) / len(self.values)

    @property
    def spread(self) -> float:
        """Half the range over seeds (0 for one value)."""
        return (max(self.values) - min(self.values)) / 2

    def text(self, digits: int = 2) -> str:
        body = f"{self.mean:.{digits}f}" + (f" ± {self.spread:.{digits}f}" if self.n > 1 else "")
        return f"{body} {self.unit}".strip()


def difference(a: Measurement, b: Measurement) -> Measurement:
    """Per-seed a - b (the seeds paired in order)."""
    if a.n != b.n:
        raise ValueError(f"cannot pair {a.n} and {b.n} seeds")
    return Measurement(tuple(x - y for x, y in zip(a.values, b.values)), a.unit)


def verdict(diff: Measurement, claim_sign: int) -> str:
    """See the module docstring."""
    if claim_sign == 0:
        return "no paper number"
    if diff.n < 2 and abs(diff.mean) < 1.0:
        return "inconclusive"
    if abs(diff.mean) <= max(diff.spread, MIN_EFFECT_DB):
        return "inconclusive"
    signs = {1 if v > 0 else -1 if v < 0 else 0 for v in diff.values}
    if signs == {claim_sign}:
        return "agrees"
    if signs == {-claim_sign}:
        return "disagrees"
    return "inconclusive"


@dataclass(frozen=True)
class ReportRow:
    """One line of report.md / report.csv."""

    table: str  # the paper's table or figure ("Tab. 1", "supp. Tab. B", ...)
    setting: str  # our capture and split, e.g. "skirt capture (synth tiny), novel pose"
    quantity: str  # "full model", "pose-only baseline", "full - baseline", ...
    protocol: str  # e.g. "eval novel_pose / bbox, PSNR"
    paper: PaperFigure
    ours: Measurement | None  # None: not run (see note)
    ssim: Measurement | None = None
    budget: str = ""
    verdict: str = ""  # one of VERDICTS; "" for a value row whose difference row carries the verdict
    sheet: str | None = None  # relative path of a comparison sheet
    note: str = ""

    def __post_init__(self) -> None:
        if self.verdict not in VERDICTS:
            raise ValueError(f"unknown verdict {self.verdict!r}")


def report_markdown(rows: list[ReportRow], title: str, preamble: str) -> str:
    """report.md: a title, the preamble (budget, seeds, machine), one table, then the disagreements listed."""
    head = ("| paper | setting | quantity | protocol | paper's figure | ours (mean ± half range) | SSIM | seeds | "
            "budget | verdict | sheet |")
    lines = [f"# {title}", "", preamble, "", head, "|" + " --- |" * 11]
    for r in rows:
        ours = r.ours.text() if r.ours is not None else f"not run: {r.note}"
        ssim = r.ssim.text(3) if r.ssim is not None else ""
        sheet = f"[sheet]({r.sheet})" if r.sheet else ""
        lines.append(f"| {r.paper.where} | {r.setting} | {r.quantity} | {r.protocol} | {r.paper.text} | {ours} | "
                     f"{ssim} | {r.ours.n if r.ours is not None else 0} | {r.budget} | {r.verdict} | {sheet} |")
    off = [r for r in rows if r.verdict == "disagrees"]
    lines += ["", "## Where our result disagrees with the paper's claim", ""]
    lines += [f"- {r.paper.where}, {r.setting}, {r.quantity}: paper {r.paper.text}, ours {r.ours.text()} "
              f"({r.protocol}). Why: (to be added)." for r in off if r.ours is not None] or ["- none"]
    against = [r for r in rows if r.verdict == "no paper number" and r.ours is not None
               and r.ours.mean < -max(r.ours.spread, MIN_EFFECT_DB)]
    if against:
        lines += ["", "## No paper number, but the full model scores below the other model here", ""]
        lines += [f"- {r.paper.where} ({r.paper.text}), {r.setting}, {r.quantity}: ours {r.ours.text()} "
                  f"({r.protocol}). Why: (to be added)." for r in against if r.ours is not None]
    undecided = [r for r in rows if r.verdict == "inconclusive"]
    if undecided:
        lines += ["", f"## Inconclusive at this budget (within the seed spread, under {MIN_EFFECT_DB} dB, or one seed "
                      "under 1 dB)", ""]
        lines += [f"- {r.paper.where}, {r.setting}, {r.quantity}: ours {r.ours.text()}" for r in undecided
                  if r.ours is not None]
    return "\n".join(lines) + "\n"


def report_csv(rows: list[ReportRow]) -> str:
    """report.csv: one row per ReportRow, per-seed values ';'-joined."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["paper", "setting", "quantity", "protocol", "paper_figure", "ours_mean", "ours_half_range",
                "ours_values", "unit", "ssim_mean", "seeds", "budget", "verdict", "sheet", "note"])
    for r in rows:
        m = r.ours
        w.writerow([r.paper.where, r.setting, r.quantity, r.protocol, r.paper.text,
                    "" if m is None else f"{m.mean:.4f}", "" if m is None else f"{m.spread:.4f}",
                    "" if m is None else ";".join(f"{v:.4f}" for v in m.values), "" if m is None else m.unit,
                    "" if r.ssim is None else f"{r.ssim.mean:.4f}", 0 if m is None else m.n, r.budget, r.verdict,
                    r.sheet or "", r.note])
    return buf.getvalue()
