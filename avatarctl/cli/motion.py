"""`avatarctl motion FILE --to anny|smpl|smplx -o OUT`: convert / retarget a motion file onto a body model."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer


def register(app: typer.Typer) -> None:
    @app.command("motion", help="Convert a motion file (anny / AMASS npz, AIST++ pkl, BVH) into a motion for anny, "
                                "SMPL or SMPL-X, retargeting it when the rigs differ; prints a summary.")
    def motion_cmd(
        source: Path = typer.Argument(..., help="Motion file: anny or AMASS (SMPL / SMPL+H / SMPL-X) .npz, AIST++ "
                                      ".pkl or .bvh."),
        to: str = typer.Option("anny", "--to", help="Target body model: anny | smpl | smplx."),
        out: Path = typer.Option(..., "-o", "--out", help="Output: OUT.npz (a motion `render --poses` reads) or "
                                 "OUT.bvh."),
        up: Optional[str] = typer.Option(None, "--up", help="Up axis of the source's world, y | z (default: the "
                                         "format's: anny / AMASS z, BVH / AIST++ y)."),
        world_up: str = typer.Option("z", "--world-up", help="Up axis of the output's world, y | z."),
        name_map: Optional[Path] = typer.Option(None, "--name-map", help="JSON {BVH joint name: SMPL-X joint name} "
                                                "for BVH files whose joint names are not built in."),
        body_model_path: Optional[Path] = typer.Option(None, "--body-model-path", help="The target's SMPL / SMPL-X "
                                                       "model file: its rest joints (shape-aware)."),
        source_model_path: Optional[Path] = typer.Option(None, "--source-model-path", help="The source's SMPL / "
                                                         "SMPL-X model file: its rest joints for the file's betas."),
    ) -> None:
        from avatarctl.cli.common import console, user_errors

        with user_errors():
            from rich.table import Table

            from avatarctl.stages import motion as stage

            cfg = stage.MotionConfig(source=str(source), to=to, out=str(out), up=up, world_up=world_up,
                                     name_map=str(name_map) if name_map else None,
                                     body_model_path=str(body_model_path) if body_model_path else None,
                                     source_model_path=str(source_model_path) if source_model_path else None)
            res = stage.run(cfg)
            t = Table(title="avatarctl motion", show_header=False)
            t.add_row("source", f"{source}  ({res.source_kind})")
            t.add_row("output", f"{res.out}  ({res.target})")
            t.add_row("frames", f"{res.frames} at {res.fps:g} fps")
            t.add_row("what", res.summary)
            if res.retargeted:
                t.add_row("joints", f"{res.mapped} mapped, {len(res.dropped)} dropped")
                t.add_row("translation", f"x{res.scale:.4g} (target / source leg length)")
                if res.floor_error_cm is not None:
                    t.add_row("feet vs floor", f"{res.floor_error_cm[0]:.1f} cm mean, {res.floor_error_cm[1]:.1f} cm "
                              "max (lowest foot joint height vs the source's, scaled)")
            for n in res.notes:
                t.add_row("note", n)
            t.add_row("time", f"{res.seconds:.1f} s")
            console.print(t)
