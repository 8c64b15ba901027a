"""`avatarctl render` / `eval` on 2 ranks (gloo, CPU): the frames are split over the ranks and the files and scores
are those of one process (only timings differ)."""

from __future__ import annotations

import csv
import json
import shutil
import time

import pytest
from fixtures.toy_capture import make_toy_capture

WAIT_S = 90


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    from avatarctl.stages import fit, ingest
    from avatarctl.stages.fit import FitRequest
    from avatarctl.stages.ingest import IngestConfig

    root = tmp_path_factory.mktemp("dist_render")
    cap, proj = make_toy_capture(root / "cap"), root / "proj"
    ingest.run(proj, IngestConfig(capture=cap, project=proj))
    fit.run(proj, FitRequest(preset="micro", iters=2, overrides=("val_every=0", "val_pairs=0"), device="cpu"),
            handle_sigint=False)
    return proj


def _files(d):
    return {p.relative_to(d).as_posix(): p.read_bytes() for p in sorted(d.rglob("*")) if p.is_file()}


def test_render_on_two_ranks_writes_the_files_of_one_process(fitted):
    from avatarctl.stages import render
    from avatarctl.stages.render import RenderConfig

    cfg = dict(frames="0:4", views=("cam01", "cam03"), background="transparent", device="cpu")
    one = render.run(fitted, RenderConfig(name="one", **cfg))
    t0 = time.perf_counter()
    two = render.run(fitted, RenderConfig(name="two", **cfg), nproc=2)
    assert time.perf_counter() - t0 < WAIT_S
    a, b = _files(one.out_dir), _files(two.out_dir)
    assert a.keys() == b.keys() and len(a) == 10  # 8 PNGs, the video, config.json (no .parts left)
    assert all(a[k] == b[k] for k in a if k != "config.json")  # PNG and MP4 bytes
    ja, jb = json.loads(a["config.json"]), json.loads(b["config.json"])
    assert [(i["file"], i["rays"]) for i in ja["images"]] == [(i["file"], i["rays"]) for i in jb["images"]]


def test_eval_on_two_ranks_scores_like_one_process(fitted):
    from avatarctl.stages import evaluate
    from avatarctl.stages.evaluate import EvalConfig

    one = evaluate.run(fitted, EvalConfig(split="train", name="one", save_images=True, device="cpu"))
    two = evaluate.run(fitted, EvalConfig(split="train", name="two", save_images=True, device="cpu"), nproc=2)
    assert [(s.frame, s.view, s.psnr, s.ssim, s.pixels) for s in one.scores] == \
        [(s.frame, s.view, s.psnr, s.ssim, s.pixels) for s in two.scores]
    assert (one.metrics.psnr, one.metrics.ssim, one.metrics.images) == (two.metrics.psnr, two.metrics.ssim, 6)
    a, b = _files(one.out_dir), _files(two.out_dir)
    assert a.keys() == b.keys() and a["sheet.png"] == b["sheet.png"]
    assert all(a[k] == b[k] for k in a if k.startswith("renders/"))
    rows = lambda d: [r[:-1] for r in csv.reader((d / "per_frame.csv").open())]  # noqa: E731 (last: seconds)
    assert rows(one.out_dir) == rows(two.out_dir)
    shutil.rmtree(two.out_dir)
