"""What would a perfect avatar score? The ceiling of the eval protocol on a synthetic capture (issue 28).

`avatarctl eval` scores a render against the project's ground truth: the ingested (undistorted, JPEG) frame times
its binary mask, over the background colour (`evaluate.protocols.GROUND_TRUTH`). Even the true scene does not score
infinity against that: the capture's images are supersampled and its mask is "coverage >= 50 %", so the mask's edge
pixels mix in the room behind the subject and the pixels just outside hold some of the subject; ingest resamples
the distorted frames bilinearly (the masks by nearest neighbour) and writes JPEG. This benchmark renders two
perfect avatars of a capture made by `avatarctl synth` and scores them as the eval does, beside an avatar's own
saved renders when given:

- **perfect (physical)**: the true scene (`CAPTURE/gt/geometry.npz`, the synth's own textures and shading) rendered
  by the synth's renderer through the capture's own (distorted) camera, supersampled as the capture was, over the
  background colour, then saved as the capture's JPEG, undistorted as ingest undistorts
  (`ingest.undistort.Undistorter`) and saved as the project's JPEG: the capture's own picture of the subject with the
  room replaced by the background colour — true geometry, colour and anti-aliasing, the same resampling and the
  same compression (its chroma subsampling blurs colour edges alike). It differs from the ground truth only on the
  mask's edge (and by the JPEG noise of a different surround).
- **perfect (mask-sharp)**: the true subject's own colour (its coverage divided out) on every pixel of the eval's
  binary mask and the background colour elsewhere: an edge as hard as the mask. Not physical; the protocol's
  ceiling (what remains is the room mixed into the mask's edge pixels, and JPEG noise).
- **avatar** (`--eval P/eval/NAME`, an eval run with `--save-images`): its renders, on its frames, views,
  background and box padding.

Each is scored on the `bbox` protocol's region (the box of the project's ingested body fit, as the eval boxes the
posed body) and split like `eval --region edge|inner` (`evaluate.regions.silhouette_band`), the edge further into
its pixels inside and outside the mask. Figures: the mean over images of the per-image PSNR (the eval's headline)
and the pooled PSNR of each region (its summed squared error over its pixels, as `eval --region` reports "pooled").

    python -m benchmarks.protocol_ceiling PROJECT [--split novel_pose|novel_view|train] [--every N]
        [--eval PROJECT/eval/NAME] [--json OUT.json]

PROJECT: a project ingested from a capture made by `avatarctl synth` (its manifest names the capture folder).
"""

from __future__ import annotations

import argparse
import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

PARTS = ("all", "edge", "inner", "edge_in_mask", "edge_out_of_mask")


@dataclass(frozen=True)
class CeilingRow:
    """One avatar's scores: per-image mean PSNR and the pooled PSNR of each part (`PARTS`; capped as the eval caps)."""

    avatar: str
    mean_image_psnr: float
    pooled_psnr: dict[str, float]
    edge_share_of_error: float  # the edge's share of the summed squared error over the box


@dataclass(frozen=True)
class CeilingReport:
    split: str
    images: int
    frames: list[int]
    views: list[str]
    supersample: int
    background: list[float]
    pixels: dict[str, int]  # per part, summed over the images
    rows: list[CeilingRow]


def mask_sharp(physical: np.ndarray, coverage: np.ndarray, mask: np.ndarray, background: np.ndarray) -> np.ndarray:
    """[H, W, 3] perfect (mask-sharp) image: the subject's own colour on the mask's pixels, the background elsewhere.

    `physical` is the subject over `background` with sub-pixel `coverage` [H, W] in [0, 1], so where coverage > 0
    the subject's colour is (physical - (1 - c) background) / c; mask pixels the subject does not cover (the
    mask was resampled by nearest neighbour) take the colour of the nearest covered pixel."""
    import cv2

    c = coverage[..., None].astype(np.float32)
    covered = coverage > 0
    subject = np.where(c > 0, (physical - (1.0 - c) * background) / np.maximum(c, 1e-6), 0.0).astype(np.float32)
    if covered.any() and (mask & ~covered).any():
        _, label = cv2.distanceTransformWithLabels((~covered).astype(np.uint8), cv2.DIST_L2, 5,
                                                   labelType=cv2.DIST_LABEL_PIXEL)
        colour_of = np.zeros((int(label.max()) + 1, 3), np.float32)
        colour_of[label[covered]] = subject[covered]
        subject = np.where(covered[..., None], subject, colour_of[label])
    return np.where(mask[..., None], subject, background).astype(np.float32)


def part_masks(box: np.ndarray, mask: np.ndarray) -> dict[str, np.ndarray]:
    """The box's pixels split as `eval --region edge|inner`, the edge further by the mask (`PARTS`)."""
    from avatarctl.evaluate.regions import silhouette_band, split_silhouette

    parts = split_silhouette(box, silhouette_band(mask))
    edge = parts["edge"]
    return {"all": box, "edge": edge, "inner": parts["inner"], "edge_in_mask": edge & mask,
            "edge_out_of_mask": edge & ~mask}


def jpeg(image: np.ndarray, quality: int) -> np.ndarray:
    """[H, W, 3] RGB float in [0, 1] or uint8 -> uint8 after a JPEG round trip at `quality` (OpenCV, as written)."""
    import cv2

    u8 = image if image.dtype == np.uint8 else np.clip(np.round(image * 255.0), 0, 255).astype(np.uint8)
    ok, buf = cv2.imencode(".jpg", u8[..., ::-1], [int(cv2.IMWRITE_JPEG_QUALITY), int(quality)])
    assert ok
    return cv2.imdecode(buf, cv2.IMREAD_COLOR)[..., ::-1]


class _Tally:
    """Summed squared error per part and per-image PSNRs of one avatar."""

    def __init__(self) -> None:
        self.sq = dict.fromkeys(PARTS, 0.0)
        self.psnrs: list[float] = []

    def add(self, image: np.ndarray, gt: np.ndarray, parts: dict[str, np.ndarray]) -> None:
        from avatarctl.evaluate.metrics import mse, psnr_from_mse

        d2 = ((image.astype(np.float64) - gt) ** 2).mean(-1)
        for k in PARTS:
            self.sq[k] += float(d2[parts[k]].sum())
        self.psnrs.append(psnr_from_mse(mse(image, gt, parts["all"])))

    def row(self, name: str, pixels: dict[str, int]) -> CeilingRow:
        from avatarctl.evaluate.metrics import psnr_from_mse
        from avatarctl.evaluate.report import PSNR_CAP

        pooled = {k: min(psnr_from_mse(self.sq[k] / pixels[k]), PSNR_CAP) if pixels[k] else float("nan")
                  for k in PARTS}
        return CeilingRow(avatar=name, mean_image_psnr=float(np.mean(np.minimum(self.psnrs, PSNR_CAP))),
                          pooled_psnr=pooled, edge_share_of_error=self.sq["edge"] / max(self.sq["all"], 1e-30))


def _read_eval(eval_dir: Path) -> dict:
    path = eval_dir / "metrics.json"
    if not path.is_file():
        raise SystemExit(f"{path} not found: pass an `avatarctl eval` output folder (PROJECT/eval/NAME)")
    metrics = json.loads(path.read_text())
    if metrics.get("protocol") != "bbox":
        raise SystemExit(f"{eval_dir} used the {metrics.get('protocol')!r} protocol; this benchmark scores bbox")
    if not (eval_dir / "renders").is_dir():
        raise SystemExit(f"{eval_dir} has no renders/: re-run that eval with --save-images")
    return metrics


def measure(project_dir: str | Path, split: str = "novel_pose", every: int = 1,
            eval_dir: str | Path | None = None) -> CeilingReport:
    import cv2

    from avatarctl.body.registry import load_body_model
    from avatarctl.evaluate.protocols import bbox_region, ground_truth
    from avatarctl.ingest.undistort import Undistorter
    from avatarctl.io.easymocap import read_easymocap_cameras
    from avatarctl.io.gt_geometry import find_gt_geometry, load_gt_geometry
    from avatarctl.io.project_io import JPEG_QUALITY, load_project_capture
    from avatarctl.project import Project
    from avatarctl.synth.capture import SceneRenderer, load_scene

    project = Project.open(project_dir)
    capture_dir = Path(project.manifest.source.path)
    gt_path = find_gt_geometry(capture_dir)
    if gt_path is None or not (capture_dir / "capture.json").is_file():
        raise SystemExit(f"{capture_dir} is not a capture made by `avatarctl synth` (no gt/geometry.npz)")
    info = json.loads((capture_dir / "capture.json").read_text())
    cap = load_project_capture(project)
    pad = 0.05
    background = np.zeros(3, np.float32)
    renders = None
    if eval_dir is not None:
        metrics = _read_eval(Path(eval_dir))
        split, frames, views = metrics["split"], [int(f) for f in metrics["frames"]], list(metrics["views"])
        background = np.asarray(metrics["background"], np.float32)
        pad = float(metrics.get("config", {}).get("bbox_pad", pad))
        renders = Path(eval_dir) / "renders"
    else:
        s = cap.split
        frames = list(s.train_frames if split in ("novel_view", "train") else s.test_frames)[::every]
        views = list(s.train_views if split == "train" else s.test_views)
    scene, geometry = load_scene(capture_dir), load_gt_geometry(gt_path)
    cams = [cap.cameras[v] for v in views]
    source = {c.name: c for c in read_easymocap_cameras(capture_dir)}
    undistort = [Undistorter.for_camera(source[v], cap.cameras[v].width / source[v].width) for v in views]
    supersample = int(info["config"]["supersample"])
    renderer = SceneRenderer(scene, [source[v] for v in views], supersample, int(info["seed"]))
    renderer.bg = [np.broadcast_to(background, b.shape).copy() for b in renderer.bg]  # the subject over the colour
    body = load_body_model(cap.body_model, cap.body_model_path)
    tallies = {name: _Tally() for name in ("perfect (physical)", "perfect (mask-sharp)")}
    if renders is not None:
        tallies["avatar"] = _Tally()
    pixels = dict.fromkeys(PARTS, 0)
    for frame in frames:
        verts = body.pose(cap.motion.for_frames([frame])).vertices[0].detach().double().numpy()
        shots = renderer.render_frame(geometry.row(frame))
        for view, cam, und, (image, cover) in zip(views, cams, undistort, shots):
            physical = jpeg(und.image(jpeg(image, int(info["config"]["jpeg_quality"]))), JPEG_QUALITY
                            ).astype(np.float32) / 255.0
            coverage = np.clip(und.image(cover.astype(np.float32)), 0.0, 1.0)
            mask = cap.mask(view, frame).astype(bool)
            gt = ground_truth(cap.image(view, frame), mask, background).astype(np.float64)
            parts = part_masks(bbox_region(cam, verts, pad=pad).mask, mask)
            for k in PARTS:
                pixels[k] += int(parts[k].sum())
            images = {"perfect (physical)": physical,
                      "perfect (mask-sharp)": mask_sharp(physical, coverage, mask, background)}
            if renders is not None:
                png = cv2.imread(str(renders / f"{frame:06d}_{view}.png"))
                if png is None:
                    raise SystemExit(f"{renders / f'{frame:06d}_{view}.png'} missing: re-run the eval with "
                                     "--save-images")
                images["avatar"] = png[..., ::-1].astype(np.float32) / 255.0
            for name, image in images.items():
                tallies[name].add(image, gt, parts)
    return CeilingReport(split=split, images=len(frames) * len(views), frames=frames, views=views,
                         supersample=supersample, background=background.tolist(), pixels=pixels,
                         rows=[t.row(name, pixels) for name, t in tallies.items()])


def main(argv: list[str] | None = None) -> CeilingReport:
    from avatarctl.atomic import write_json

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("project")
    ap.add_argument("--split", default="novel_pose", choices=("novel_pose", "novel_view", "train"))
    ap.add_argument("--every", type=int, default=1, help="every Nth frame of the split (without --eval)")
    ap.add_argument("--eval", type=Path, default=None, help="an eval output folder with renders/: score them too, "
                    "on its frames and views")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    if args.every < 1:
        raise SystemExit("--every must be >= 1")
    r = measure(args.project, args.split, args.every, args.eval)
    share = 100.0 * r.pixels["edge"] / max(r.pixels["all"], 1)
    print(f"{r.split}, bbox protocol, {r.images} images ({len(r.frames)} frames x {len(r.views)} views), the capture "
          f"{r.supersample}x{r.supersample} supersampled; the edge band {share:.1f} % of the box's pixels")
    print(f"  {'avatar':<21} {'mean PSNR':>9}  {'pooled: all':>11} {'edge':>6} {'inner':>6} {'edge in':>7} "
          f"{'edge out':>8}  {'edge share':>10}")
    for row in r.rows:
        p = row.pooled_psnr
        print(f"  {row.avatar:<21} {row.mean_image_psnr:9.2f}  {p['all']:11.2f} {p['edge']:6.2f} {p['inner']:6.2f} "
              f"{p['edge_in_mask']:7.2f} {p['edge_out_of_mask']:8.2f}  {100 * row.edge_share_of_error:9.1f}%")
    if args.json is not None:
        write_json(args.json, asdict(r), indent=1)  # atomic
    return r


if __name__ == "__main__":
    main()
