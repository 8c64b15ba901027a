"""`avatarctl ingest CAPTURE PROJECT`: a raw capture -> a project directory (see avatarctl/ingest/pipeline.py)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer


def register(app: typer.Typer) -> None:
    from avatarctl.cli.common import WAIT_HELP

    @app.command("ingest", help="Turn a raw capture (frames, cameras, masks, body fits) into a project directory.")
    def ingest(
        capture: Path = typer.Argument(..., help="Capture folder (EasyMocap, ZJU-MoCap, THuman4.0, PeopleSnapshot, "
                                                 "COLMAP, ActorsHQ, or `avatarctl synth` output), or ONE video file "
                                                 "(or a "
                                                 "folder of its frames) from a static phone. Never modified."),
        project: Path = typer.Argument(..., help="Project directory to create (must not exist or be empty)."),
        format: str = typer.Option("auto", "--format",
                                   help="auto | easymocap | zju | thuman4 | peoplesnapshot | colmap | dna_rendering | "
                                        "4d_dress | video"),
        body_model: Optional[str] = typer.Option(None, "--body-model",
                                                 help="anny | smpl | smplx (default: what the capture's fits are; "
                                                      "anny for --fits keypoints)"),
        body_model_path: Optional[Path] = typer.Option(None, "--body-model-path",
                                                       help="SMPL / SMPL-X model file (.pkl or .npz)."),
        masks: str = typer.Option("auto", "--masks", help="auto (files, else mediapipe if installed, else "
                                                          "background) | files | "
                                                          "background (matting against background/<cam>.jpg seeded "
                                                          "by the body mesh) | mediapipe (person segmentation; pip "
                                                          "install 'avatarctl[capture]')"),
        fits: str = typer.Option("auto", "--fits", help="auto | files (motion.npz / smpl/*.json) | keypoints "
                                                        "(MediaPipe keypoints -> triangulation -> a fit of "
                                                        "--body-model: anny, or smpl / smplx with "
                                                        "--body-model-path)"),
        keypoint_fit_iters: int = typer.Option(400, "--keypoint-fit-iters",
                                               help="Adam steps of the body fit to the keypoints (--fits keypoints)."),
        keypoint_silhouette: Optional[float] = typer.Option(
            None, "--keypoint-silhouette", help="Weight of the keypoint fit's silhouette term (keeps the projected "
                                                "body inside the masks); 0 = off; default: the fit's own."),
        keypoint_outline: Optional[float] = typer.Option(
            None, "--keypoint-outline", help="Weight of the keypoint fit's outline term (the masks' outline pulls the "
                                             "body out to it; loose clothes pull it to the cloth); 0 = off; default: "
                                             "3 for one video, else off."),
        keypoint_offsets: bool = typer.Option(True, "--keypoint-offsets/--no-keypoint-offsets",
                                              help="anny fits: place each keypoint where MediaPipe puts it on a body "
                                                   "(its hips higher than anny's, ...), not at anny's own COCO point."),
        refine_masks: bool = typer.Option(True, "--refine-masks/--no-refine-masks",
                                          help="--masks mediapipe: refine each mask's outline against the camera's "
                                               "background: background/<cam>.jpg, else estimated from its frames "
                                               "(static cameras)."),
        frames: Optional[str] = typer.Option(None, "--frames",
                                             help="Frame numbers: start:stop[:step] (stop exclusive) or a,b,c."),
        views: Optional[str] = typer.Option(None, "--views", help="Comma-separated camera names (default: all)."),
        resize: float = typer.Option(1.0, "--resize", help="Scale factor after undistortion, e.g. 0.5."),
        contact_sheet: bool = typer.Option(True, "--contact-sheet/--no-contact-sheet",
                                           help="Write ingest/contact_sheet.png (frames with the body overlaid)."),
        focal_px: Optional[float] = typer.Option(None, "--focal-px", help="One video: focal length in pixels of "
                                                 "its frames (default: the video's metadata, else a phone's main "
                                                 "camera, 26 mm equivalent)."),
        fov_deg: Optional[float] = typer.Option(None, "--fov-deg", help="One video: diagonal field of view in "
                                                "degrees (instead of --focal-px)."),
        height: Optional[float] = typer.Option(None, "--height", help="One video: the person's height in metres, "
                                               "the body fit's scale prior (default 1.70)."),
        benchmark: Optional[str] = typer.Option(None, "--benchmark", help="A named benchmark protocol of the "
                                                "capture's dataset (docs/formats.md, 'Benchmark protocols'): its "
                                                "train/test frames and views and its scale; `avatarctl eval` then "
                                                "scores under it."),
        wait: bool = typer.Option(False, "--wait", help=WAIT_HELP),
    ) -> None:
        from rich.table import Table

        from avatarctl.cli.common import console, progress_bar, user_errors
        from avatarctl.lists import split_list
        from avatarctl.stages import ingest as stage

        with user_errors():
            cfg = stage.IngestConfig(capture=capture, project=project, format=format, body_model=body_model,
                               body_model_path=body_model_path, masks=masks, fits=fits,
                               keypoint_fit_iters=keypoint_fit_iters, keypoint_silhouette=keypoint_silhouette,
                               keypoint_outline=keypoint_outline,
                               keypoint_offsets=keypoint_offsets, refine_masks=refine_masks,
                               frames=frames,
                               views=None if views is None else split_list(views), resize=resize,
                               contact_sheet=contact_sheet, focal_px=focal_px, fov_deg=fov_deg, height_m=height,
                               benchmark=benchmark)
            if cfg.format == "auto":
                fmt, reason = stage.detect(cfg.capture)
                console.print(f"detected format [bold]{fmt}[/]: {reason}")
            with progress_bar("ingest", ("part",), out=console) as bar:
                task = bar.add_task("frames", total=None, part="")
                res = stage.run(cfg.project, cfg, wait=wait,
                                progress=lambda p: bar.update(task, completed=p.done, total=p.total, part=p.part))

            t = Table(title=f"ingest -> {res.project}")
            t.add_column("item")
            t.add_column("value")
            t.add_row("format", res.format)
            shown = ", ".join(res.cameras[:8]) + (" …" if len(res.cameras) > 8 else "")
            t.add_row("cameras", f"{len(res.cameras)} ({shown})")
            t.add_row("frames", f"{len(res.frames)} ({res.frames[0]}..{res.frames[-1]})")
            t.add_row("resolution", f"{res.resolution[0]}x{res.resolution[1]} (undistorted, pinhole)")
            for n in res.notes:
                if n.startswith("intrinsics: "):
                    t.add_row("intrinsics", n.removeprefix("intrinsics: "))
            t.add_row("body model", res.body_model)
            t.add_row("masks", res.masks_source)
            t.add_row("body fits", res.fits_source)
            if res.estimate is not None:
                for item, value in res.estimate.rows(fitted=res.fits_source == "keypoints"):
                    t.add_row(item, value)
            t.add_row("mesh inside masks", f"{100 * res.vertices_inside_masks:.1f}% of vertices")
            if res.camera_colour is not None:
                g = res.camera_colour
                est = g.gain[g.estimated]
                t.add_row("camera colour", f"{int(g.estimated.sum())} of {len(g.views)} cameras, gains "
                          f"{est.min():.2f}-{est.max():.2f} of the training cameras' mean (ingest/camera_colour.json)"
                          if len(est) else "no camera shares enough body points with a training camera")
            t.add_row("time", f"{res.seconds:.1f} s")
            console.print(t)
            for n in res.notes:
                if not n.startswith("intrinsics: "):
                    console.print(f"note: {n}")
            for w in res.warnings:
                console.print(f"[yellow]warning:[/] {w}")
