"""`avatarctl eval PROJECT`: score renders against held-out ground truth; `--compare` tabulates several projects."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer


def register(app: typer.Typer) -> None:
    from avatarctl.cli.common import WAIT_HELP

    @app.command("eval", help="Score renders against held-out ground truth (PSNR/SSIM, bbox or full protocol).")
    def eval_cmd(
        projects: list[Path] = typer.Argument(..., help="Project directory (with --compare: several)."),
        split: Optional[str] = typer.Option(None, "--split", help="novel_view (training frames, held-out views; "
                                            "default) | novel_pose (test frames, held-out views) | train."),
        protocol: Optional[str] = typer.Option(None, "--protocol", help="bbox (Neural Body: PSNR inside the "
                                               "projected 3D body box, SSIM on its rectangle; default) | full | "
                                               "mpmavatar (both images times the eroded, blurred mask, near-white "
                                               "zeroed) | mpmavatar_4d_dress (without the white cut)."),
        benchmark: Optional[str] = typer.Option(None, "--benchmark", help="A named benchmark protocol "
                                                "(docs/formats.md, 'Benchmark protocols'): its split, pixel protocol "
                                                "and background. Default: the one the project was ingested with "
                                                "(`ingest --benchmark`), unless --split / --protocol are given; "
                                                "none: ignore it."),
        test_project: Optional[Path] = typer.Option(None, "--test-project", help="The project of a benchmark's "
                                                    "test recording (4D-DRESS: the other take, ingested with the "
                                                    "same --benchmark): its test frames and cameras are scored, "
                                                    "the avatar driven by its body fits."),
        frames: Optional[str] = typer.Option(None, "--frames", help="Frames within the split: all | a:b[:step] | "
                                             "3,7,9."),
        views: Optional[str] = typer.Option(None, "--views", help="Comma list of cameras (default: the split's)."),
        every: int = typer.Option(1, "--every", help="Keep every N-th frame (Neural Body's protocol: 30)."),
        latent: str = typer.Option("auto", "--latent", help="auto (mean for training frames; novel poses: "
                                   "0, or the training mean with model.novel_latent=train_mean) | mean | zero | "
                                   "sample."),
        seed: int = typer.Option(0, "--seed", help="Seed for --latent sample."),
        name: Optional[str] = typer.Option(None, "--name", help="Output folder PROJECT/eval/NAME (default: "
                                           "<split>_<protocol>)."),
        sheet: int = typer.Option(4, "--sheet", help="Images shown in the comparison sheet (0 = none)."),
        max_rays: int = typer.Option(8192, "--max-rays", help="Rays per model call (memory bound)."),
        device: str = typer.Option("auto", "--device", help="auto | cpu | cuda."),
        checkpoint: Optional[Path] = typer.Option(None, "--checkpoint", help="Checkpoint file (default: latest)."),
        save_images: bool = typer.Option(False, "--save-images", help="Also write each render to "
                                         "eval/NAME/renders/<frame>_<view>.png (bbox protocol: only the box is "
                                         "rendered, the rest is background)."),
        region: str = typer.Option("all", "--region", help="What the headline PSNR is over: all (the protocol's "
                                   "region) | garment | body | edge | inner. garment/body need the capture's "
                                   "ground-truth geometry (synth writes gt/geometry.npz; a 4D-DRESS take has "
                                   "labelled scans); with it every eval also "
                                   "reports both. edge (within 1 px of the mask's silhouette, either side) / inner "
                                   "(the rest): any capture; reports these two instead."),
        knockout: Optional[str] = typer.Option(None, "--knockout", help="Render-time knockout of the trained "
                                               "model (paper Fig. 3 / supp. node-variable table): delta-n and/or embedding, comma-separated: "
                                               "that variable is set to zero when rendering."),
        camera_colour: str = typer.Option("auto", "--camera-colour", help="auto: a held-out camera is rendered "
                                          "through its colour gains that ingest estimated from the body's colours "
                                          "across cameras (ingest/camera_colour.json) | off: in the training "
                                          "cameras' mean colour."),
        refine_pose: int = typer.Option(0, "--refine-pose", help="STEPS > 0: also score each frame after its body "
                                        "pose is refined against that frame's images for STEPS steps with the "
                                        "avatar frozen (the monocular papers' test-time protocol; reported apart "
                                        "from the plain figure, with its own sheet). Gaussian local fields only. "
                                        "e.g. 40."),
        refine_pose_from: str = typer.Option("images", "--refine-pose-from", help="What --refine-pose fits each "
                                             "pose to: images (colours and masks: the monocular papers' protocol) | "
                                             "masks (the frame's masks alone, not its colours: the avatar's "
                                             "silhouette, clothes included; slower to converge: e.g. "
                                             "--refine-pose 80)."),
        held_out_poses: str = typer.Option("fit", "--held-out-poses", help="What drives the held-out frames "
                                           "(novel_pose): fit (the poses the fit found for them with the avatar's "
                                           "silhouette against the training views' masks, where it did: estimated "
                                           "body fits; else ingest's) | ingest (ingest's body fits)."),
        compare: bool = typer.Option(False, "--compare", help="Do not render: print a side-by-side table of the "
                                     "projects' latest metrics.json (same split/protocol), e.g. "
                                     "`avatarctl eval FULL --compare ABL1 ABL2`."),
        nproc: int = typer.Option(1, "--nproc", help="Split the frames over N ranks of this machine (same scores "
                                  "as one process). Clusters: torchrun ... -m avatarctl eval ..."),
        wait: bool = typer.Option(False, "--wait", help=WAIT_HELP),
    ) -> None:
        from avatarctl.cli.common import console, user_errors
        from avatarctl.errors import InputError

        with user_errors():
            if compare:
                _compare(projects, split, protocol, console)
                return
            if len(projects) > 1:
                raise InputError(f"{len(projects)} projects given", fix="pass one PROJECT, or add --compare to "
                                 "tabulate several")
            from avatarctl.lists import split_list
            from avatarctl.stages.common import parse_knockout
            from avatarctl.stages.evaluate import EvalConfig

            view_names = split_list(views)
            if benchmark not in (None, "none") and (split or protocol):
                raise InputError(f"--benchmark {benchmark} sets the split and the protocol",
                                 fix="drop --split / --protocol, or --benchmark")
            cfg = EvalConfig(split=split or "novel_view", protocol=protocol or "bbox", name=name, frames=frames,
                             benchmark=benchmark or ("none" if split or protocol else "auto"),
                             views=view_names, every=every, latent=latent, seed=seed, sheet_rows=sheet,
                             max_rays_per_chunk=max_rays, device=device,
                             checkpoint=str(checkpoint) if checkpoint else None, save_images=save_images,
                             region=region, knockout=parse_knockout(knockout),
                             test_project=str(test_project) if test_project else None,
                             camera_colour=camera_colour, refine_pose=refine_pose,
                             refine_pose_from=refine_pose_from, held_out_poses=held_out_poses)
            _run(projects[0], cfg, nproc, wait, console)


def _run(project: Path, cfg, nproc: int, wait: bool, console) -> None:
    from rich.table import Table

    from avatarctl.cli.common import progress_bar
    from avatarctl.stages import evaluate
    from avatarctl.progress import ProgressReport

    with progress_bar("eval", ("info",), out=console) as bar:
        task = bar.add_task("eval", total=None, info="loading avatar")

        def progress(p: ProgressReport) -> None:
            info = f"{p.done / max(p.seconds, 1e-9):.2f} images/s"
            if p.detail is not None:
                info += f" | last {p.detail.psnr:.2f} dB"
            bar.update(task, total=p.total, completed=p.done, info=info)

        res = evaluate.run(project, cfg, progress=progress, nproc=nproc, wait=wait)
    if res is None:  # a torchrun rank > 0: rank 0 reports
        return

    m = res.metrics
    t = Table(title=f"avatarctl eval — {m.split} / {m.protocol}", show_header=False)
    t.add_row("PSNR" + ("" if m.region == "all" else f" ({m.region})"),
              f"{m.psnr:.3f} dB  (std {m.psnr_std:.2f}, min {m.psnr_min:.2f}, max {m.psnr_max:.2f})")
    for rname, r in (m.regions or {}).items():
        t.add_row(f"  {rname} region", (f"{r['psnr']:.3f} dB" if r["psnr"] is not None else "empty")
                  + f"  ({r['share_of_pixels']:.1%} of the pixels, {r['share_of_error']:.1%} of the squared error;"
                  f" pooled {r['pooled_psnr'] or float('nan'):.2f} dB; its best flat colour "
                  f"{r['flat_colour_psnr'] or float('nan'):.2f} dB)")
    if m.camera_colour is not None:  # held-out cameras through ingest's gains (issue 51)
        gains = "; ".join(f"{v} x{','.join(f'{g:.2f}' for g in gs)}" for v, gs in m.camera_colour["gain"].items())
        t.add_row("camera colour", f"held-out cameras rendered through ingest's gains ({gains}; "
                  "--camera-colour off: the training cameras' mean)")
    if m.colour_matched is not None:  # NeRF-W's protocol, apart from the plain figure (issue 51)
        cm = m.colour_matched
        gains = "; ".join(f"{v} x{','.join(f'{g:.2f}' for g in gs)}" for v, gs in cm["gain"].items())
        t.add_row("PSNR colour-matched", f"{cm['psnr']:.3f} dB  (NeRF-W: each camera's colour fitted on the left "
                  f"half, scored on the right half; plain on the same halves {cm['plain_psnr']:.3f} dB; gains "
                  f"{gains})")
    if m.held_out_poses is not None:  # the fit's poses of the held-out frames (issue 51)
        hp = m.held_out_poses
        t.add_row("held-out poses", f"{hp['frames']} of {hp['of']} frames driven by the fit's poses (ingest's "
                  f"refined against the masks of {', '.join(hp['views'])} with the avatar's silhouette; "
                  "--held-out-poses ingest: ingest's)")
    if m.refined_pose is not None:  # held-out poses refined, apart from the plain figure (issue 51)
        rp = m.refined_pose
        t.add_row("PSNR refined pose", f"{rp['psnr']:.3f} dB  SSIM {rp['ssim']:.4f}  (each frame's body pose "
                  f"refined against its {rp['target']}, avatar frozen, {rp['steps']} steps; plain "
                  f"{rp['plain_psnr']:.3f} dB; "
                  f"root moved {rp['shift_cm']:.1f} cm on average, joints up to {rp['max_angle_deg']:.1f} deg; "
                  f"{rp['seconds']:.0f} s)")
    t.add_row("SSIM", f"{m.ssim:.4f}  (skimage {m.metric_settings['scikit_image']}, "
                      f"win {m.metric_settings['ssim']['win_size']}, data_range 1)")
    t.add_row("LPIPS", f"{m.lpips:.4f}" if m.lpips is not None else f"absent: {m.lpips_reason}")
    t.add_row("images", f"{m.images} = {len(m.frames)} frames x {len(m.views)} views "
                        f"({', '.join(m.views)}); every {m.every}")
    t.add_row("latent / background", f"{m.latent} / {','.join(f'{c:g}' for c in m.background)}")
    t.add_row("ground truth", m.ground_truth)
    t.add_row("checkpoint step", str(m.checkpoint_step))
    if m.benchmark is not None:
        t.add_row("benchmark", m.benchmark + ("" if not m.not_comparable else
                                              "  [yellow]not comparable:[/] " + "; ".join(m.not_comparable)))
        for fig in m.comparable_with or []:
            t.add_row("  comparable with", fig)
    if m.test_project is not None:
        t.add_row("test project", m.test_project)
    t.add_row("time", f"{res.seconds:.1f} s ({m.timing['seconds_per_image']:.2f} s per image render)")
    console.print(t)
    for w in res.warnings:
        console.print(f"[yellow]warning:[/] {w}", soft_wrap=True)
    console.print(f"metrics: {res.out_dir / 'metrics.json'}", soft_wrap=True)
    if (res.out_dir / "sheet.png").is_file():
        console.print(f"sheet:   {res.out_dir / 'sheet.png'}", soft_wrap=True)
    if (res.out_dir / "sheet_refined.png").is_file():
        console.print(f"sheet after pose refinement: {res.out_dir / 'sheet_refined.png'}", soft_wrap=True)


def _compare(projects: list[Path], split, protocol, console) -> None:
    from rich.table import Table

    from avatarctl.stages.evaluate import compare

    rows = compare(projects, split, protocol)
    t = Table(title=f"avatarctl eval --compare — {rows[0].split} / {rows[0].protocol}")
    t.add_column("project")
    t.add_column("model")
    for col in ("PSNR dB", "SSIM", "LPIPS", "images", "step"):
        t.add_column(col, justify="right", no_wrap=True)
    for r in rows:
        flag = "" if r.same_images else " [yellow]*[/]"
        t.add_row(Path(r.project).name, r.label, f"{r.psnr:.3f}", f"{r.ssim:.4f}",
                  "-" if r.lpips is None else f"{r.lpips:.4f}", f"{r.images}{flag}", str(r.checkpoint_step))
    console.print(t)
    if not all(r.same_images for r in rows):
        console.print("[yellow]*[/] evaluated other (frame, view) images than the first project: "
                      "not directly comparable")
    for r in rows:
        console.print(f"{Path(r.project).name}: {r.metrics_path}", soft_wrap=True)
