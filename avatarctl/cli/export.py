"""`avatarctl export PROJECT`: posed meshes (GLB / PLY / OBJ) and an animatable skinned glTF avatar."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer


def register(app: typer.Typer) -> None:
    from avatarctl.cli.common import WAIT_HELP

    @app.command("export", help="Export a fitted avatar: posed meshes (GLB / PLY / OBJ, marching cubes of the density "
                                "with baked colours) and avatar.glb, a skinned glTF 2.0 mesh with the body's "
                                "skeleton and the motion as an animation.")
    def export_cmd(
        project: Path = typer.Argument(..., help="Project directory with a fit (`avatarctl fit`)."),
        frames: Optional[str] = typer.Option(None, "--frames", help="Posed meshes of these frames: all | train | "
                                             "test | a:b[:step] | 3,7,9 (with --poses, the motion file's). "
                                             "Default: the first training frame."),
        poses: Optional[Path] = typer.Option(None, "--poses", help="Motion file (as for `avatarctl render`): the "
                                             "posed frames and the animation of avatar.glb. Default: the "
                                             "project's own frames."),
        formats: str = typer.Option("glb,ply", "--format", help="Comma list: posed meshes glb, ply, obj; for a "
                               "Gaussian-field avatar also splat (splats/<frame>.ply, 3DGS layout) and player "
                               "(player.html: plays the frames without Python; 30 frames without --frames)."),
        posed: bool = typer.Option(True, "--posed/--no-posed", help="Write posed meshes."),
        skinned: bool = typer.Option(True, "--skinned/--no-skinned", help="Write avatar.glb (rest-pose mesh, "
                                     "skeleton, skinning weights, animation)."),
        voxel: float = typer.Option(0.008, "--voxel", help="Grid spacing of the density sampling, metres."),
        threshold: str = typer.Option("auto", "--threshold", help="Density level of the surface, 1/metre (lower: "
                                      "fuller cloth, more haze; higher: holes in soft regions), or auto: levels "
                                      "around the field's density just inside the body model's skin (at most 10), "
                                      "the one whose mesh looks most like the training photographs."),
        influences: int = typer.Option(4, "--influences", help="Skinning weights per vertex in avatar.glb: 4 (every "
                                       "glTF viewer) or 8 (a second JOINTS_1 / WEIGHTS_1 set: closer to the body "
                                       "model, read by Blender, not by three.js)."),
        latent: str = typer.Option("auto", "--latent", help="auto | mean | zero | sample (posed meshes)."),
        seed: int = typer.Option(0, "--seed", help="Seed for --latent sample."),
        recenter: bool = typer.Option(True, "--recenter/--no-recenter", help="With --poses: start the motion where "
                                      "the avatar's first training frame stands."),
        score: bool = typer.Option(False, "--score", help="Also render each posed mesh and the volume in the "
                                   "held-out views and report both PSNRs (eval bbox protocol)."),
        name: str = typer.Option("default", "--name", help="Output folder PROJECT/export/NAME (replaced)."),
        device: str = typer.Option("auto", "--device", help="auto | cpu | cuda."),
        checkpoint: Optional[Path] = typer.Option(None, "--checkpoint", help="Checkpoint file (default: "
                                                  "fit/checkpoints/latest.pt)."),
        wait: bool = typer.Option(False, "--wait", help=WAIT_HELP),
    ) -> None:
        from avatarctl.cli.common import console, user_errors

        with user_errors():
            from avatarctl.lists import split_list
            from avatarctl.stages.export import ExportConfig

            cfg = ExportConfig(name=name, frames=frames, posed=posed, skinned=skinned,
                               poses=str(poses) if poses else None,
                               formats=split_list(formats), voxel=voxel,
                               threshold=_threshold(threshold), influences=influences, latent=latent, seed=seed,
                               recenter=recenter, score=score,
                               device=device, checkpoint=str(checkpoint) if checkpoint else None)
            _run(project, cfg, wait, console)


def _threshold(text: str) -> float | None:
    from avatarctl.errors import InputError

    if text.strip().lower() == "auto":
        return None
    try:
        return float(text)
    except ValueError:
        raise InputError(f"--threshold {text!r} is not a number", where="--threshold",
                         fix="use auto or a density in 1/metre, e.g. --threshold 10") from None


def _run(project: Path, cfg, wait: bool, console) -> None:
    from rich.table import Table

    from avatarctl.cli.common import progress_bar
    from avatarctl.stages import export
    from avatarctl.progress import ProgressReport

    with progress_bar("export", ("part",), out=console) as bar:
        task = bar.add_task("export", total=None, part="loading avatar")

        def progress(p: ProgressReport) -> None:
            bar.update(task, total=p.total, completed=p.done, part=p.part)

        res = export.run(project, cfg, progress=progress, wait=wait)

    t = Table(title="avatarctl export", show_header=False)
    t.add_row("output", str(res.out_dir))
    if res.level is not None:
        c = res.level.choice
        tried = ", ".join(f"{'*' if s.step == c.step else ''}{s.level:.3g}/m "
                          + (f"{s.psnr:.2f} dB" if s.psnr is not None else "no surface")
                          for s in sorted(c.candidates, key=lambda s: s.level))
        t.add_row("surface level", f"{c.level:.3g}/m = {c.factor:.3g} x body level {c.body_level:.3g}/m, the best of "
                  f"{tried} (frame {res.level.frame}, training views {', '.join(c.views)}; {c.seconds:.1f} s)")
    for m in res.meshes:
        t.add_row(f"frame {m.frame}", f"{m.vertices:,} vertices, {m.faces:,} faces, level {m.threshold:.3g}/m, "
                  f"{m.pieces} piece(s) (largest {100 * m.largest_piece:.0f} %), {m.seconds:.1f} s: "
                  + ", ".join(f"{f} ({b / 1e6:.1f} MB)" for f, b in m.files.items()))
    if res.avatar is not None:
        a = res.avatar
        t.add_row("avatar", f"{a.file}: {a.vertices:,} vertices (level {a.threshold:.3g}/m, {a.pieces} piece(s), "
                  f"largest {100 * a.largest_piece:.0f} %), {a.joints} joints, {a.animation_frames} animation "
                  f"frames ({a.animation_source}), {a.bytes / 1e6:.1f} MB, {a.seconds:.1f} s")
        r = a.reload
        t.add_row("reload check", f"max vertex error {r['vs_lbs_same_weights_max_m'] * 1000:.3g} mm vs our LBS "
                  f"(same weights), {r['vs_lbs_dense_weights_max_m'] * 1000:.3g} mm vs dense weights"
                  if r.get("checked") else f"skipped: {r['reason']}")
    if res.splats:
        t.add_row("splats", ", ".join(f"{f} ({b / 1e6:.1f} MB)" for f, b in list(res.splats.items())[:3])
                  + (f" ... ({len(res.splats)} files)" if len(res.splats) > 3 else ""))
    mean = res.mean_psnr()
    if mean is not None:
        t.add_row("PSNR (held-out views)", f"mesh {mean[0]:.2f} dB, volume {mean[1]:.2f} dB "
                  f"({len(res.scores)} images, bbox)")
    t.add_row("checkpoint step", str(res.checkpoint_step))
    t.add_row("time", f"{res.seconds:.1f} s")
    console.print(t)
