"""`avatarctl synth OUT`: make a synthetic ground-truth capture (anny body + simulated skirt), EasyMocap layout."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer


def register(app: typer.Typer) -> None:
    @app.command("synth", help="Make a synthetic ground-truth capture (anny body + simulated dress) in EasyMocap "
                               "layout: calibrated distorted cameras, images, masks, background plates, body fits.")
    def _cmd(
        out: Path = typer.Argument(..., help="Output capture directory (must not exist or be empty)."),
        preset: str = typer.Option("tiny", "--preset", help="tiny (~6 views, 24+12 frames, 96px, <1 min), "
                                   "small (12 views, 80+40, 256px), standard (20 views, 300+150, 512px); "
                                   "micro (4 views, 6+4, 64px) for tests; the paper's other settings at tiny "
                                   "sizes: monocular (1 training camera + 3 evaluation-only ones, the subject "
                                   "turning in an A-pose, no skirt; 24+8) and tight (tiny without the skirt); "
                                   "phone: the monocular scene as ONE portrait video (288x512, 40+12 frames), "
                                   "OUT/video.mp4, the truth under OUT/gt/; realistic: 4 cameras (3 train), 128 px, "
                                   "24+12 frames with every imperfection of a real capture (the options below)."),
        seed: int = typer.Option(0, "--seed", help="Seed of every random choice; same seed, same files."),
        views: Optional[int] = typer.Option(None, "--views", help="Override the number of cameras.", hidden=True),
        train_frames: Optional[int] = typer.Option(None, "--train-frames", help="Override training frames.",
                                                   hidden=True),
        test_frames: Optional[int] = typer.Option(None, "--test-frames", help="Override test frames.", hidden=True),
        size: Optional[int] = typer.Option(None, "--size", help="Override the image size (pixels).", hidden=True),
        width: Optional[int] = typer.Option(None, "--width", help="Override the image width (pixels; 0: square).",
                                            hidden=True),
        supersample: Optional[int] = typer.Option(None, "--supersample", help="Rays per pixel along each axis, "
                                                  "1-4 (box-filtered: the pixel integrates its area, as a camera "
                                                  "sensor does); default: the preset's."),
        fit_noise: Optional[str] = typer.Option(None, "--fit-noise", help="DEG,CM[,FRAMES]: write body fits that "
                                                "are off like real ones (each joint rotation N(0, DEG^2) degrees, "
                                                "root N(0, CM^2) cm; per frame, or drifting over about FRAMES "
                                                "frames); the true fits go to gt/motion.npz. E.g. 2,1 or 2,1,5."),
        exposure: Optional[float] = typer.Option(None, "--exposure", help="Cameras that disagree in exposure: "
                                                 "each camera's images x 2^N(0, EV^2) (stops); e.g. 0.25."),
        white_balance: Optional[float] = typer.Option(None, "--white-balance", help="...and in white balance: each "
                                                      "channel x 2^N(0, STOPS^2); e.g. 0.05."),
        held_out_ev: Optional[float] = typer.Option(None, "--held-out-ev", help="...and the evaluation-only "
                                                    "cameras EV stops brighter (< 0: darker) on top; e.g. 0.25."),
        noise: Optional[float] = typer.Option(None, "--noise", help="Sensor noise: N(0, STD^2) per pixel and channel "
                                              "(images in [0, 1]); e.g. 0.01."),
        jpeg_quality: Optional[int] = typer.Option(None, "--jpeg-quality", help="JPEG quality of images and plates "
                                                   "(default 95; e.g. 80)."),
        shutter: Optional[float] = typer.Option(None, "--shutter", help="Motion blur: exposure time in seconds, "
                                                "e.g. 0.0167 (1/60 s); 0: none."),
        masks: Optional[str] = typer.Option(None, "--masks", help="truth: write the true masks; none: leave them "
                                            "to ingest (`--masks mediapipe`), the truth under OUT/gt/masks/."),
        fits: Optional[str] = typer.Option(None, "--fits", help="truth: write the body fits (exact, or --fit-noise); "
                                           "none: leave them to ingest (`--fits keypoints`), the truth in "
                                           "OUT/gt/motion.npz."),
        clean: bool = typer.Option(False, "--clean", help="The preset's clean twin: the same capture (seed, scene) "
                                   "without any of the imperfections above."),
    ) -> None:
        from avatarctl.cli.common import console, user_errors

        with user_errors():
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

            from avatarctl.stages import synth as stage
            from avatarctl.progress import ProgressReport

            overrides = {k: v for k, v in dict(views=views, train_frames=train_frames, test_frames=test_frames,
                                                size=size, width=width, supersample=supersample, exposure_ev=exposure,
                                                white_balance=white_balance, held_out_ev=held_out_ev, noise_std=noise,
                                                jpeg_quality=jpeg_quality, shutter_s=shutter, masks=masks,
                                                fits=fits).items()
                         if v is not None}
            if fit_noise is not None:
                overrides.update(_fit_noise(fit_noise))
            config = stage.SynthConfig.preset(preset, seed, **overrides)
            if clean:
                config = config.clean_twin()
            console.print(f"synth [bold]{preset}[/] seed {seed}: {config.views} views, {config.train_frames}+"
                          f"{config.test_frames} frames, {config.image_width}x{config.size}px, {config.supersample}x"
                          f"{config.supersample} rays per pixel -> {out}")
            with Progress(TextColumn("{task.description:<9}"), BarColumn(), MofNCompleteColumn(),
                          TimeElapsedColumn(), console=console, transient=False) as bar:
                tasks: dict[str, int] = {}

                def progress(p: ProgressReport) -> None:
                    if p.part not in tasks:
                        tasks[p.part] = bar.add_task(p.part, total=p.total)
                    bar.update(tasks[p.part], completed=p.done)

                res = stage.run(out, config, progress)
            if config.imperfections:
                console.print("  imperfections: " + ", ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}"
                                                               for k, v in config.imperfections.items())
                              + (" (ingest with --masks mediapipe)" if config.masks == "none" else "")
                              + (" (ingest with --fits keypoints)" if config.fits == "none" else ""))
            t = res.timings
            console.print(f"[green]wrote[/] {res.out}: {len(res.cameras)} cameras "
                          f"(train {', '.join(res.train_views)}; test {', '.join(res.test_views)}), "
                          f"{len(res.train_frames)} train + {len(res.test_frames)} test frames")
            if config.layout == "video":
                console.print(f"  one video: {res.out / 'video.mp4'} (camera {res.cameras[0].name}); the truth "
                              f"(calibration, masks, fits of every camera): {res.out / 'gt' / 'capture'}")
            if config.garment == "skirt":
                console.print(f"  skirt hem radius {res.hem_radius_range[0]:.2f}-{res.hem_radius_range[1]:.2f} m, "
                              f"max particles inside the body {res.max_penetrating_particles}")
            else:
                console.print("  no garment (tight clothing)")
            if res.hem_pair:
                hp = res.hem_pair
                console.print(f"  same pose, different hem: frames {hp['frames'][0]} and {hp['frames'][1]} "
                              f"(body {hp['body_rms_m'] * 1000:.2f} mm RMS apart, hem {hp['hem_rms_m']:.3f} m)")
            console.print(f"  time: anny {t['anny_s']:.1f} s, simulate {t['simulate_s']:.1f} s "
                          f"({t['simulate_s_per_frame']:.3f} s/frame), render {t['render_s']:.1f} s, "
                          f"total {t['total_s']:.1f} s; contact sheet {res.sheet}")


def _fit_noise(spec: str) -> dict[str, float]:
    from avatarctl.errors import InputError
    from avatarctl.lists import split_list

    try:
        parts = list(split_list(spec, float))
        if len(parts) not in (2, 3):
            raise ValueError
    except ValueError:
        raise InputError(f"cannot read --fit-noise {spec!r}", where="--fit-noise",
                         fix="give DEG,CM or DEG,CM,FRAMES, e.g. --fit-noise 2,1 or 2,1,5") from None
    return {"fit_noise_deg": parts[0], "fit_noise_cm": parts[1], "fit_noise_corr_frames": (parts + [0.0])[2]}
