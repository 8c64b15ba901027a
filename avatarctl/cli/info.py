"""`avatarctl info PROJECT`: what a project directory holds."""

from __future__ import annotations

from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    @app.command("info", help="Print what a project directory holds (manifest, stages, outputs).")
    def info(project: Path = typer.Argument(..., help="Project directory.")) -> None:
        from rich.table import Table

        from avatarctl.cli.common import console, user_errors
        from avatarctl.project import Project

        with user_errors():
            proj = Project.open(project)
            m = proj.manifest
            console.print(f"[bold]{proj.root}[/]  schema_version={m.schema_version}  created={m.created}")
            console.print(f"body model: {m.body_model.to_json()}")
            src = m.source
            console.print(f"source: {src.path}  format={src.format}  sha256={src.sha256[:16]}…  files={src.files}")
            t = Table(title="stage runs")
            for col in ("stage", "finished", "version", "outputs", "summary"):
                t.add_column(col)
            for rec in m.stages:
                missing = [o for o in rec.outputs if not (proj.root / o).exists()]
                outs = f"{len(rec.outputs)}" + (f" ([red]{len(missing)} missing[/])" if missing else "")
                summ = ", ".join(f"{k}={v}" for k, v in list(rec.summary.items())[:6])
                t.add_row(rec.stage, rec.finished, rec.version, outs, summ)
            console.print(t)
