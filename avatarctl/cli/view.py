"""`avatarctl view PROJECT`: a local web viewer of a fitted avatar (orbit camera, frames, motion, latent mode)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer


def register(app: typer.Typer) -> None:
    @app.command("view", help="Open a local web viewer of a fitted avatar: orbit camera, frame slider over "
                              "training and test frames or motion files, play, latent mode, server render and save "
                              "video buttons. A Gaussian-field avatar is drawn by the browser (our WebGL2 page); a "
                              "ray-marched one is rendered progressively with a mesh preview (viser's page). Ctrl-C "
                              "stops it.")
    def view_cmd(
        project: Path = typer.Argument(..., help="Project directory with a fit (`avatarctl fit`)."),
        poses: Optional[list[Path]] = typer.Option(None, "--poses", help="Motion file to play (as for `avatarctl "
                                                   "render`; repeat for several, the page switches between them and "
                                                   "loads others). Default: the project's frames first."),
        port: int = typer.Option(8080, "--port", help="Port to serve on."),
        host: str = typer.Option("127.0.0.1", "--host", help="Interface to serve on (0.0.0.0: other machines)."),
        resolution: Optional[int] = typer.Option(None, "--resolution", help="Longer image side at full quality, "
                                                 "pixels (default: 512 on a GPU, 256 on the CPU)."),
        latent: str = typer.Option("auto", "--latent", help="auto | mean | zero | sample (also in the page)."),
        seed: int = typer.Option(0, "--seed", help="Seed for --latent sample."),
        fps: Optional[float] = typer.Option(None, "--fps", help="Play speed, frames per second (default: the "
                                            "motion's frame rate; also in the page)."),
        mesh_preview: bool = typer.Option(True, "--mesh-preview/--no-mesh-preview", help="Ray-marched avatars: the "
                                          "page draws the frame's posed mesh while the server render refines."),
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
                             poses=tuple(str(p) for p in poses or ()), recenter=recenter, fps=fps, device=device,
                             mesh_preview=mesh_preview,
                             checkpoint=str(checkpoint) if checkpoint else None)
            console.print("loading the avatar ...")

            def ready(url: str) -> None:
                console.print(f"[bold green]viewer ready:[/] {url}   (Ctrl-C to stop)", soft_wrap=True)

            try:
                view.run(project, cfg, ready=ready)
            except KeyboardInterrupt:
                console.print("viewer stopped")
