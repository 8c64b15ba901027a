"""`avatarctl demo OUT`: synth -> ingest -> fit -> render -> eval on a synthetic capture, end to end."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer


def register(app: typer.Typer) -> None:
    @app.command("demo", help="Run synth -> ingest -> fit -> render -> eval end to end on a synthetic capture.")
    def demo_cmd(
        out: Path = typer.Argument(..., help="New folder for the demo (OUT/capture, OUT/project)."),
        preset: str = typer.Option("tiny", "--preset", help="ci (alias micro: ~1 min, plumbing only) | tiny (a "
                                   "recognisable avatar; the fit takes most of the time) | small (an hour or more)."),
        seed: int = typer.Option(0, "--seed", help="Seed of the synthetic capture and of the fit."),
        iters: Optional[int] = typer.Option(None, "--iters", help="Fit steps (default: the preset's)."),
        device: str = typer.Option("auto", "--device", help="auto | cpu | cuda."),
    ) -> None:
        from avatarctl.cli.common import console, user_errors

        with user_errors():
            from avatarctl.stages.demo import DemoConfig

            _run(DemoConfig(out=out, preset=preset, seed=seed, iters=iters, device=device), console)


def _run(cfg, console) -> None:
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
    from rich.table import Table

    from avatarctl.stages import demo
    from avatarctl.progress import ProgressReport
    from avatarctl.stages.demo import StageDone

    s = cfg.sizes
    budget = s.fit_settings.get("time_budget_s")
    steps = f"{s.iters} steps" + (f" or {budget:g} s, whichever comes first" if budget else "")
    console.print(f"[bold]avatarctl demo[/] preset {cfg.preset}: synth {s.synth}, fit {s.fit_preset} for {steps}, "
                  f"orbit {s.orbit_views} views at {s.orbit_resolution} px -> {cfg.out}")
    with Progress(TextColumn("{task.description:<18}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  console=console) as bar:
        tasks: dict[str, int] = {}

        def progress(p: ProgressReport) -> None:
            if p.stage not in tasks:
                tasks[p.stage] = bar.add_task(p.stage, total=p.total)
            bar.update(tasks[p.stage], completed=p.done, total=p.total)

        def on_stage(st: StageDone) -> None:
            if st.stage in tasks and "stopped by" in st.summary:  # a fit the time budget ended: the bar ends full
                done = int(st.summary["steps"])
                bar.update(tasks[st.stage], total=done, completed=done,
                           description=f"{st.stage} ({st.summary['stopped by'].split(' (')[0]})")
            t = Table(title=f"{st.stage}  ({st.seconds:.1f} s)", show_header=False, title_justify="left")
            for k, v in st.summary.items():
                t.add_row(k, str(v))
            bar.console.print(t)

        res = demo.run(cfg.out, cfg, progress=progress, on_stage=on_stage)

    t = Table(title=f"avatarctl demo ({cfg.preset}) done in {res.seconds / 60:.1f} min")
    for col in ("split", "PSNR (bbox)", "SSIM", "images"):
        t.add_column(col)
    for split, m in res.metrics.items():
        t.add_row(split, f"{m.psnr:.2f} dB", f"{m.ssim:.4f}", str(m.images))
    console.print(t)
    for name, path in res.videos.items():
        console.print(f"video ({name}): {path}", soft_wrap=True)
    for split, path in res.metrics_paths.items():
        console.print(f"metrics ({split}): {path}", soft_wrap=True)
