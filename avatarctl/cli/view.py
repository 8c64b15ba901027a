"""`avatarctl view PROJECT`: a local web viewer of a fitted avatar (orbit camera, frames, motion, latent mode)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer


def register(app: typer.Typer) -> None:
    @app.command("view", help="Open a local web viewer of a fitted avatar (viser): orbit camera, frame slider over "
                              "training and test frames or a motion file, latent mode, resolution; low resolution "
                              "while the camera moves, full when it rests. Ctrl-C stops it.")
    def view_cmd(
        project: Path = typer.Argument(..., help="Project directory with a fit (`avatarctl fit`)."),
        poses: Optional[Path] = typer.Option(None, "--poses", help="Motion file to play (as for `avatarctl "
                                             "render`). Default: the project's training and test frames."),
        port: int = typer.Option(8080, "--port", help="Port to serve on."),
        host: str = typer.Option("127.0.0.1", "--host", help="Interface to serve on (0.0.0.0: other machines)."),
        resolution: Optional[int] = typer.Option(None, "--resolution", help="Longer image side at full quality, "
                                                 "pixels (default: 512 on a GPU, 256 on the CPU)."),
        latent: str = typer.Option("auto", "--latent", help="auto | mean | zero | sample (also in the page)."),
        seed: int = typer.Option(0, "--seed", help="Seed for --latent sample."),
        fps: float = typer.Option(10.0, "--fps", help="Play speed, frames per second."),
        recenter: bool = typer.Option(True, "--recenter/--no-recenter", help="With --poses: start the motion where "
                                      "the avatar's first training frame stands."),
        device: str = typer.Option("auto", "--device", help="auto | cpu | cuda."),
        checkpoint: Optional[Path] = typer.Option(None, "--checkpoint", help="Checkpoint file (default: "
                                                  "fit/checkpoints/latest.pt)."),
    ) -> None:
        from avatarctl.cli.common import console, user_errors

        with user_errors():
            from avatarctl.stages import view
            from avatarctl.stages.view import ViewConfig

            cfg = ViewConfig(host=host, port=port, resolution=resolution, latent=latent, seed=seed,
                             poses=str(poses) if poses else None, recenter=recenter, fps=fps, device=device,
                             checkpoint=str(checkpoint) if checkpoint else None)
            console.print("loading the avatar ...")

            def ready(url: str) -> None:
                console.print(f"[bold green]viewer ready:[/] {url}   (Ctrl-C to stop)", soft_wrap=True)

            try:
                view.run(project, cfg, ready=ready)
            except KeyboardInterrupt:
                console.print("viewer stopped")
