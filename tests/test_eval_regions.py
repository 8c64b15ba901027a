"""`avatarctl eval --region garment|body`: the garment's own score from a capture's ground-truth geometry; `--region
edge|inner`: the silhouette band's and the rest's, from the masks."""

from __future__ import annotations

import numpy as np
import pytest
from fixtures.toy_capture import make_toy_capture

from avatarctl.errors import InputError
from avatarctl.geometry.cameras import Camera


def _quad(z: float, x0: float, x1: float) -> tuple[np.ndarray, np.ndarray]:
    v = np.array([[x0, -0.5, z], [x1, -0.5, z], [x1, 0.5, z], [x0, 0.5, z]], np.float64)
    return v, np.array([[0, 1, 2], [0, 2, 3]])


def test_garment_mask_is_depth_ordered_and_grown():
    from avatarctl.evaluate.regions import GROW_PX, garment_mask, split_region

    K = np.array([[40.0, 0, 31.5], [0, 40.0, 31.5], [0, 0, 1]])
    cam = Camera(name="c", K=K, R=np.eye(3), T=np.zeros(3), dist=np.zeros(5), width=64, height=64)
    garment_v, garment_f = _quad(3.0, -0.5, 0.5)  # far, centred: x in [-0.5, 0.5] m -> u in [25, 38]
    body_v, body_f = _quad(2.0, 0.0, 1.0)  # near, covers the garment's right half
    m = garment_mask(cam, body_v, body_f, garment_v, garment_f)
    row = m[32]
    assert row[26:31].all() and not row[33:40].any(), "the body in front hides the garment's right half"
    assert row[26 - GROW_PX] and not row[26 - GROW_PX - 2], "grown by GROW_PX pixels"
    # drawn the other way round (garment in front) the whole quad is garment
    m2 = garment_mask(cam, *_quad(4.0, 0.0, 1.0), *_quad(3.0, -0.5, 0.5))
    assert m2[32, 26:38].all()
    box = np.zeros((64, 64), bool)
    box[10:50, 10:50] = True
    parts = split_region(box, m)
    assert (parts["garment"] | parts["body"]).sum() == box.sum() and not (parts["garment"] & parts["body"]).any()


def test_silhouette_band_is_the_mask_boundary_either_side():
    from avatarctl.evaluate.regions import EDGE_PX, silhouette_band, split_silhouette

    m = np.zeros((20, 30), bool)
    m[5:15, 8:20] = True  # 10 x 12
    band = silhouette_band(m)
    assert EDGE_PX == 1 and band.sum() == 12 * 14 - 8 * 10  # dilated by one minus eroded by one
    assert band[5, 10] and band[4, 10] and not band[6, 10] and not band[3, 10] and not band[10, 14]
    edge = np.zeros((20, 30), bool)
    edge[:, :10] = True  # touches the image's left border: only its right side is a silhouette
    assert silhouette_band(edge).sum() == 20 * 2 and not silhouette_band(edge)[:, 0].any()
    box = np.zeros((20, 30), bool)
    box[2:18, 2:28] = True
    parts = split_silhouette(box, band)
    assert (parts["edge"] | parts["inner"]).sum() == box.sum() and not (parts["edge"] & parts["inner"]).any()


def _write_gt(cap, tmp_path):
    """gt/geometry.npz for the toy capture: the body and, as its 'garment', the lower half of the body grown 2 %."""
    from fixtures.toy_capture import toy_motion

    from avatarctl.body.toy import ToyBody
    from avatarctl.io.gt_geometry import GT_GEOMETRY

    body = ToyBody()
    motion = toy_motion(4)
    faces = body.template(motion).faces.numpy()
    verts = body.pose(motion).vertices.numpy()
    lower = faces[(verts[0][faces][:, :, 1].mean(1) < 0)]
    (cap / GT_GEOMETRY).parent.mkdir()
    np.savez(cap / GT_GEOMETRY, frame_index=np.arange(4), body_vertices=verts, body_faces=faces,
             garment_vertices=verts * 1.02, garment_faces=lower)


def test_eval_reports_garment_and_body_regions(tmp_path):
    from avatarctl.stages import evaluate, fit, ingest
    from avatarctl.stages.evaluate import EvalConfig
    from avatarctl.stages.fit import FitRequest
    from avatarctl.stages.ingest import IngestConfig

    cap, proj = make_toy_capture(tmp_path / "cap"), tmp_path / "proj"
    ingest.run(proj, IngestConfig(capture=cap, project=proj))
    fit.run(proj, FitRequest(preset="micro", iters=2, overrides=("val_every=0",), device="cpu"), handle_sigint=False)
    with pytest.raises(InputError, match="ground-truth garment geometry"):
        evaluate.run(proj, EvalConfig(region="garment", device="cpu", sheet_rows=0))
    plain = evaluate.run(proj, EvalConfig(device="cpu", sheet_rows=0, name="plain"))
    assert plain.metrics.regions is None and plain.metrics.region == "all"
    # the silhouette split needs only the masks: edge + inner recombine into the whole region
    sil = evaluate.run(proj, EvalConfig(region="edge", device="cpu", sheet_rows=0, name="edge"))
    e, i = sil.metrics.regions["edge"], sil.metrics.regions["inner"]
    assert sil.metrics.psnr == pytest.approx(e["psnr"]) and 0 < e["share_of_pixels"] < 1
    assert e["pixels"] + i["pixels"] == sum(s.pixels for s in sil.scores)
    assert e["share_of_error"] + i["share_of_error"] == pytest.approx(1.0)
    header = (sil.out_dir / "per_frame.csv").read_text().splitlines()[0]
    assert header.endswith("edge_psnr,edge_pixels,inner_psnr,inner_pixels")

    _write_gt(cap, tmp_path)
    res = evaluate.run(proj, EvalConfig(region="garment", device="cpu", sheet_rows=0))
    m = res.metrics
    g, b = m.regions["garment"], m.regions["body"]
    assert m.region == "garment" and m.psnr == pytest.approx(g["psnr"])
    assert 0 < g["share_of_pixels"] < 1 and g["share_of_pixels"] + b["share_of_pixels"] == pytest.approx(1.0)
    assert g["share_of_error"] + b["share_of_error"] == pytest.approx(1.0)
    assert g["flat_colour_psnr"] is not None and b["flat_colour_psnr"] is not None
    assert g["pixels"] + b["pixels"] == sum(s.pixels for s in res.scores)
    # the pooled errors of the two regions recombine into the whole region's error
    whole = sum(s.mse * s.pixels for s in res.scores) / sum(s.pixels for s in res.scores)
    parts = (g["pixels"] * 10 ** (-g["pooled_psnr"] / 10) + b["pixels"] * 10 ** (-b["pooled_psnr"] / 10)) \
        / (g["pixels"] + b["pixels"])
    assert parts == pytest.approx(whole, rel=1e-6)
    assert m.psnr != pytest.approx(plain.metrics.psnr)  # the headline is the garment's, not the box's
    header = (res.out_dir / "per_frame.csv").read_text().splitlines()[0]
    assert header.endswith("garment_psnr,garment_pixels,body_psnr,body_pixels")
    with pytest.raises(InputError, match="unknown region"):
        EvalConfig(region="skirt")
