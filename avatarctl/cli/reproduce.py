"""`avatarctl reproduce OUT`: re-run the paper's quantitative claims on synthetic captures into one report."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer


def register(app: typer.Typer) -> None:
    @app.command("reproduce", help="Re-run the paper's tables (Tab. 1, Tab. 2, supp. Tab. B / C, the sparse-"
                                   "evaluation claim) on synthetic captures: OUT/report.md + report.csv. Resumable: "
                                   "re-run the same command to finish an interrupted run.")
    def reproduce_cmd(
        out: Path = typer.Argument(..., help="Output folder (new, or the OUT of an interrupted run to resume)."),
        budget_steps: Optional[int] = typer.Option(400, "--budget-steps", help="Fit steps per model (7 models per "
                                                   "seed)."),
        minutes: Optional[float] = typer.Option(None, "--minutes", help="Fit time in all, minutes, split evenly "
                                                "over the fits (with --budget-steps: whichever ends first)."),
        seeds: int = typer.Option(2, "--seeds", help="Fit seeds per model (>= 2 gives mean ± half range)."),
        scale: str = typer.Option("tiny", "--scale", help="tiny (synth tiny / tight / monocular, fit preset cpu-mlp) | "
                                  "micro (seconds; plumbing only, for tests)."),
        bench: bool = typer.Option(True, "--bench/--no-bench", help="Run `python -m benchmarks.bench` for the "
                                   "sparse-evaluation row (needs a source checkout)."),
        device: str = typer.Option("auto", "--device", help="auto | cpu | cuda."),
    ) -> None:
        from avatarctl.cli.common import console, user_errors

        with user_errors():
            from avatarctl.stages.reproduce import ReproduceConfig

            cfg = ReproduceConfig(budget_steps=budget_steps, minutes=minutes, seeds=seeds, scale=scale, bench=bench,
                                  device=device)
            _run(out, cfg, console)


def _run(out: Path, cfg, console) -> None:
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
    from rich.table import Table

    from avatarctl.stages import reproduce
    from avatarctl.progress import ProgressReport
    from avatarctl.stages.reproduce import UnitDone

    console.print(f"[bold]avatarctl reproduce[/] scale {cfg.scale}, {cfg.budget_text()}, {cfg.seeds} seeds -> {out}")
    with Progress(TextColumn("{task.description:<40}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  console=console, transient=True) as bar:
        tasks: dict[str, int] = {}

        def progress(p: ProgressReport) -> None:
            if p.stage not in tasks:
                tasks[p.stage] = bar.add_task(p.stage[:40], total=p.total)
            bar.update(tasks[p.stage], completed=p.done, total=p.total)

        def on_unit(u: UnitDone) -> None:
            bar.console.print(f"[{u.index}/{u.total}] {u.kind} {u.name}: {u.summary} ({u.seconds:.0f} s)")

        res = reproduce.run(out, cfg, progress=progress, on_unit=on_unit)

    t = Table(title=f"avatarctl reproduce: done in {res.seconds / 60:.1f} min ({cfg.budget_text()})")
    for col in ("paper", "capture", "quantity", "ours", "verdict"):
        t.add_column(col)
    for r in res.rows:
        t.add_row(r.paper.where, r.setting.split(" ")[0], r.quantity,
                  r.ours.text() if r.ours is not None else f"not run ({r.note})", r.verdict)
    console.print(t)
    console.print(f"report: {res.report_md}", soft_wrap=True)
    console.print(f"csv:    {res.report_csv}", soft_wrap=True)
