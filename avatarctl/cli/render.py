"""`avatarctl render PROJECT`: render novel views / novel poses of a fitted avatar to PNG frames and an MP4."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

FRAMES_HELP = ("Frames: all | train | test | a:b[:step] | 3,7,9 (frame numbers; with --poses, the motion file's). "
               "Default: all.")


def register(app: typer.Typer) -> None:
    from avatarctl.cli.common import WAIT_HELP

    @app.command("render", help="Render novel views / novel poses of a fitted avatar to PNG frames and MP4.")
    def render_cmd(
        project: Path = typer.Argument(..., help="Project directory with a fit (`avatarctl fit`)."),
        poses: Optional[Path] = typer.Option(None, "--poses", help="Motion file to animate the avatar with: anny "
                                             "npz (as written by `avatarctl synth`), AMASS npz (SMPL / SMPL+H / "
                                             "SMPL-X), AIST++ pkl or BVH; retargeted onto the avatar's body model "
                                             "when made for another (said in the summary). Default: the project's "
                                             "own frames."),
        frames: Optional[str] = typer.Option(None, "--frames", help=FRAMES_HELP),
        views: Optional[str] = typer.Option(None, "--views", help="Comma list of capture cameras. Default: the "
                                            "first held-out view."),
        orbit: int = typer.Option(0, "--orbit", help="Render N cameras over one full turn around the subject "
                                  "instead of capture views (the frames are spread over the turn)."),
        elevation: Optional[float] = typer.Option(None, "--elevation", help="Orbit elevation in degrees (default: "
                                                  "the capture cameras' mean)."),
        radius: Optional[float] = typer.Option(None, "--radius", help="Orbit radius in metres (default: the "
                                               "capture cameras' mean distance)."),
        latent: str = typer.Option("auto", "--latent", help="auto (z = mu for training frames; novel "
                                   "poses: 0, or the training mean with model.novel_latent=train_mean) | mean | zero "
                                   "| sample."),
        seed: int = typer.Option(0, "--seed", help="Seed for --latent sample."),
        resolution: Optional[int] = typer.Option(None, "--resolution", help="Longer image side in pixels "
                                                 "(default: the capture's)."),
        name: str = typer.Option("default", "--name", help="Output folder: PROJECT/render/NAME (replaced if it "
                                 "exists)."),
        background: str = typer.Option("fit", "--background", help="fit (the colour the avatar was trained over) "
                                       "| black | white | transparent (RGBA PNGs) | r,g,b."),
        fps: Optional[float] = typer.Option(None, "--fps", help="Video frame rate (default: the motion's fps / "
                                            "frame step)."),
        recenter: bool = typer.Option(True, "--recenter/--no-recenter", help="With --poses: move the motion so its "
                                      "first frame stands where the avatar's first training frame stands."),
        max_rays: int = typer.Option(8192, "--max-rays", help="Rays per model call: bounds peak memory, whatever "
                                     "the image size (lower it if memory is short)."),
        device: str = typer.Option("auto", "--device", help="auto | cpu | cuda."),
        checkpoint: Optional[Path] = typer.Option(None, "--checkpoint", help="Checkpoint file (default: "
                                                  "fit/checkpoints/latest.pt)."),
        knockout: Optional[str] = typer.Option(None, "--knockout", help="Render-time knockout of the trained "
                                               "model (paper Fig. 3 / supp. node-variable table): delta-n and/or "
                                               "embedding, comma-separated: that variable is set to zero when "
                                               "rendering; recorded in config.json."),
        nproc: int = typer.Option(1, "--nproc", help="Split the video frames over N ranks of this machine (same "
                                  "files as one process). Clusters: torchrun ... -m avatarctl render ..."),
        wait: bool = typer.Option(False, "--wait", help=WAIT_HELP),
    ) -> None:
        from avatarctl.cli.common import console, user_errors

        with user_errors():
            from avatarctl.lists import split_list
            from avatarctl.stages.common import parse_knockout
            from avatarctl.stages.render import RenderConfig

            view_names = split_list(views)
            cfg = RenderConfig(name=name, poses=str(poses) if poses else None, frames=frames, views=view_names,
                               orbit=orbit, elevation=elevation, radius=radius, latent=latent, seed=seed,
                               resolution=resolution, background=background, fps=fps, recenter=recenter,
                               max_rays_per_chunk=max_rays, device=device,
                               checkpoint=str(checkpoint) if checkpoint else None,
                               knockout=parse_knockout(knockout))
            _run(project, cfg, nproc, wait, console)


def _run(project: Path, cfg, nproc: int, wait: bool, console) -> None:
    from rich.table import Table

    from avatarctl.cli.common import progress_bar
    from avatarctl.stages import render
    from avatarctl.progress import ProgressReport

    with progress_bar("render", ("speed",), out=console) as bar:
        task = bar.add_task("render", total=None, speed="loading avatar")

        def progress(p: ProgressReport) -> None:
            bar.update(task, total=p.total, completed=p.done, speed=f"{p.per_second:.2f} frames/s")

        res = render.run(project, cfg, progress=progress, nproc=nproc, wait=wait)
    if res is None:  # a torchrun rank > 0: rank 0 reports
        return

    t = Table(title="avatarctl render", show_header=False)
    t.add_row("output", str(res.out_dir))
    t.add_row("video", f"{res.video}  ({res.video_size[0]}x{res.video_size[1]}, {res.fps:g} fps, H.264 yuv420p)")
    t.add_row("images", f"{len(res.images)} PNG, {res.width}x{res.height}"
              + ("  (RGBA)" if cfg.background == "transparent" else ""))
    t.add_row("motion", res.motion_source)
    if res.retarget:
        t.add_row("retarget", res.retarget)
    t.add_row("latent", ", ".join(f"{k}: {v}" for k, v in res.latent_counts.items()))
    t.add_row("background", ",".join(f"{c:.3g}" for c in res.background))
    if cfg.knockout:
        t.add_row("knockout", ", ".join(cfg.knockout) + " set to zero")
    t.add_row("checkpoint step", str(res.checkpoint_step))
    t.add_row("time", f"{res.seconds:.1f} s total, {res.seconds_per_image:.2f} s per image")
    console.print(t)
    console.print(f"video: {res.video}", soft_wrap=True)
