"""`avatarctl fit PROJECT`: parse options -> `FitRequest` -> `avatarctl.stages.fit.run` -> rich summary."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

def register(app: typer.Typer) -> None:
    from avatarctl.cli.common import WAIT_HELP
    from avatarctl.stages.fit import preset_help

    @app.command("fit", help="Train the avatar (structured local radiance fields + per-node cVAEs) on a project.")
    def _cmd(
        project: Path = typer.Argument(..., help="Project directory written by `avatarctl ingest`."),
        iters: Optional[int] = typer.Option(None, "--iters", help="Total optimisation steps (default: the preset's)."),
        preset: Optional[str] = typer.Option(None, "--preset", help=preset_help()),
        resume: bool = typer.Option(False, "--resume", help="Continue from fit/checkpoints/latest.pt (same config; "
                                                            "only --iters may change)."),
        fresh: bool = typer.Option(False, "--fresh", help="Discard an existing fit of this project and start over."),
        seed: Optional[int] = typer.Option(None, "--seed", help="Seed of the model init, ray sampling and noise."),
        device: str = typer.Option("auto", "--device", help="auto | cpu | cuda."),
        overrides: Optional[list[str]] = typer.Option(None, "--set", help="Override a config value: key=value "
                                                      "(FitConfig field, model.<field> or model.<group>.<field>); "
                                                      "repeatable."),
        ablation: Optional[str] = typer.Option(None, "--ablation", help="Comma list of: no-delta-n, no-embedding, "
                                               "deterministic, per-frame-latent, lbs-baseline."),
        nproc: int = typer.Option(1, "--nproc", help="Train data-parallel on N ranks of this machine (gloo on CPU, "
                                  "NCCL on GPUs); the batch options stay the global batch. Clusters: torchrun "
                                  "--nproc_per_node N -m avatarctl fit ..."),
        shards: Optional[int] = typer.Option(None, "--shards", help="Ray shards (default: the number of ranks); a "
                                             "fit samples the same rays on any --nproc dividing them."),
        wait: bool = typer.Option(False, "--wait", help=WAIT_HELP),
    ) -> None:
        from avatarctl.cli.common import console, user_errors

        with user_errors():
            _run(project, iters, preset, resume, fresh, seed, device, overrides or [], ablation, nproc, shards, wait,
                 console)


def _run(project_dir: Path, iters, preset, resume, fresh, seed, device, overrides, ablation, nproc, shards, wait,
         console) -> None:
    from rich.table import Table

    from avatarctl.cli.common import progress_bar
    from avatarctl.stages import fit
    from avatarctl.progress import ProgressReport

    cfg = fit.FitRequest(preset=preset, iters=iters, seed=seed, overrides=tuple(overrides), ablation=ablation,
                         device=device, resume=resume, fresh=fresh, nproc=nproc, shards=shards, wait=wait)
    plan = fit.prepare(project_dir, cfg)  # option errors before the progress bar
    project = plan.project
    if not fit.is_main_rank():  # a torchrun rank > 0: train quietly, rank 0 reports
        fit.run(project_dir, cfg, plan=plan)
        return
    with progress_bar("fit", ("speed", "info"), out=console, bar_width=24) as bar:
        task = bar.add_task("fit", total=None, speed="", info="setting up")
        state = {"last_t": None, "last_step": None}

        def progress(p: ProgressReport) -> None:
            import time

            if p.part == "held-out poses":  # after the steps: the held-out frames posed (fit/held_out_poses.py)
                bar.update(task, info=f"posing the held-out frames: {p.done} / {p.total}")
                return
            rep = p.detail  # the loop's StepReport
            if bar.tasks[task].total is None:
                bar.update(task, total=rep.iters, completed=rep.start_step)
            now = time.perf_counter()
            if state["last_t"] is None:
                state["last_t"], state["last_step"] = now, rep.step - 1
            it_s = (rep.step - state["last_step"]) / max(now - state["last_t"], 1e-9)
            info = " ".join(f"{k} {rep.losses[k]:.4g}" for k in ("mse", "kl") if k in rep.losses)
            if rep.val_psnr is not None:
                info += f" | val {rep.val_psnr:.2f} dB"
            bar.update(task, completed=rep.step, speed=f"{it_s:.2f} it/s", info=info)

        result = fit.run(project_dir, cfg, progress=progress, plan=plan)

    table = Table(title="avatarctl fit", show_header=False)
    table.add_row("project", str(project.root))
    note = {"interrupted": "  [yellow](interrupted)[/]", "time_budget": "  (time budget reached)"}
    table.add_row("steps", f"{result.step} / {result.iters}" + note.get(result.stop_reason, ""))
    table.add_row("device", result.device)
    table.add_row("preset / ablations", f"{result.config.preset} / {', '.join(result.config.ablations) or 'none'}")
    table.add_row("time", f"{result.seconds:.1f} s training + {result.setup_seconds:.1f} s set-up")
    table.add_row("rays/s", f"{result.rays_per_s:.0f}")
    table.add_row("losses", " ".join(f"{k} {v:.4g}" for k, v in result.losses.items()))
    if result.val is not None and result.val.psnr is not None:
        pairs = ", ".join(f"{p.view}@{p.frame} {p.psnr:.2f}" for p in result.val.pairs)
        table.add_row("held-out PSNR (bbox)", f"{result.val.psnr:.2f} dB  ({pairs})")
    if result.refinement is not None:
        r = result.refinement
        table.add_row("pose refinement", f"{r.frames} frames x {r.joints} joints: mean {r.mean_rotation_deg:.2f} deg "
                                         f"(max {r.max_rotation_deg:.2f}), root {r.mean_root_shift_cm:.2f} cm"
                      + (f" -> {r.path}" if r.path else " (kept in the checkpoint: no motion file for this body model)"))
    if result.hull_nodes is not None:  # model.hull_nodes on: what the masks showed beyond the body, what was placed
        table.add_row("hull nodes", result.hull_nodes.removeprefix("hull: "))
    if result.garment_tracking is not None:  # `track` on: what the garment tracking pass did or why it did not run
        table.add_row("garment tracking", result.garment_tracking.removeprefix("garment tracking: "))
    if result.held_out_poses is not None:  # `held_out_poses` on: the held-out frames posed by the avatar's silhouette
        h = result.held_out_poses
        table.add_row("held-out poses", f"skipped: {h['skipped']}" if "skipped" in h else
                      f"{h['frames']} of {h['held_out']} held-out frames posed ({h['moved']} moved) against the "
                      f"masks of {', '.join(h['views'])}: mask loss {h['mask_loss_before']:.4f} -> "
                      f"{h['mask_loss_after']:.4f}; {h['seconds']:.0f} s -> {h['path']}")
    table.add_row("checkpoint", str(result.checkpoint))
    table.add_row("log / config", f"{project.paths.fit_log} / {project.paths.fit_config}")
    console.print(table)
    if result.interrupted:
        console.print(f"[yellow]stopped early[/]: continue with `avatarctl fit {project.root} --resume`")
