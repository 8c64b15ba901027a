"""`ingest --benchmark NAME`: the capture side of a named benchmark protocol (`avatarctl.evaluate.benchmarks`).

`plan_benchmark` checks that the capture is the protocol's (its format, its recording when the reader can tell,
its held-out cameras, images no smaller than the protocol's scale) and decides:
- the frames: the protocol's train and test frames that the capture holds (a partial download ingests what it
  has; `--frames` narrows them further), at least one of each. A novel_view protocol's test frames are training
  frames seen from the held-out cameras: the split's test_frames stay empty and eval scores the protocol's test
  frames. A protocol whose test frames are another recording (`test_sequence`, 4D-DRESS's other take) is two
  projects: the training recording (training frames, every training camera, none held out) and the test recording
  (test frames and test cameras only, nothing to train on), told apart by `CaptureSource.sequence`;
- the views: every ingested camera; the protocol's test views held out, the rest train (`--views` may narrow the
  training cameras, never drop a test view);
- the resize: the protocol's scale over the capture's own (`CaptureSource.release_scale`);
- the record written to ``ingest/benchmark.json`` (`io.project_io.IngestedBenchmark`), whose `partial` lists
  every way the project falls short of the protocol (eval prints it beside the figures).
"""

from __future__ import annotations

from dataclasses import dataclass

from avatarctl.errors import InputError
from avatarctl.evaluate.benchmarks import BenchmarkProtocol, for_dataset
from avatarctl.frames import select_frames
from avatarctl.io.capture import CaptureSource, fmt_list
from avatarctl.io.project_io import IngestedBenchmark, Split


@dataclass(frozen=True)
class BenchmarkPlan:
    frames: list[int]  # ascending capture frame numbers to ingest
    cams: list[str]  # cameras to ingest (capture order): the selected ones; a test recording's test views only
    split: Split
    resize: float
    record: IngestedBenchmark
    notes: list[str]


def check_dataset(proto: BenchmarkProtocol, src: CaptureSource) -> None:
    """Refuse a protocol made for another dataset or another recording (one line, naming the ones that fit)."""
    if src.format != proto.dataset:
        fitting = for_dataset(src.format)
        raise InputError(f"--benchmark {proto.name} is for {proto.dataset} captures; this capture is {src.format}",
                         where=str(src.root), fix=f"use one of: {', '.join(fitting)}" if fitting else
                         f"drop --benchmark (no protocol is defined for {src.format})")
    ours = [q for q in (proto.sequence, proto.test_sequence) if q]
    if ours and src.sequence and src.sequence not in ours:
        other = [n for n in for_dataset(src.format) if src.sequence in _sequences_of(n)]
        raise InputError(f"--benchmark {proto.name} is for {' and '.join(ours)}; this capture is {src.sequence}",
                         where=str(src.root), fix=f"use {other[0]}" if other else
                         f"no protocol is defined for {src.sequence}: drop --benchmark")
    if proto.test_sequence and not src.sequence:
        raise InputError(f"--benchmark {proto.name} trains on {proto.sequence} and scores {proto.test_sequence}; "
                         "this capture's folders do not say which it is", where=str(src.root),
                         fix=f"keep the release's folder names ({proto.sequence})")


def _sequences_of(name: str) -> tuple[str | None, str | None]:
    from avatarctl.evaluate.benchmarks import benchmark

    p = benchmark(name)
    return p.sequence, p.test_sequence


def plan_benchmark(proto: BenchmarkProtocol, src: CaptureSource, cams: list[str], available: list[int],
                   frames_spec: str | None, views_given: bool) -> BenchmarkPlan:
    """What ingest does under `proto` (see the module docstring). `cams`: the selected cameras (capture order);
    `available`: the frame numbers those cameras have; `frames_spec`: `--frames` (None: all)."""
    check_dataset(proto, src)
    resize = proto.scale / src.release_scale
    notes = [f"benchmark {proto.name}: {len(proto.test_views)} held-out views, train frames {proto.train_frames}, "
             f"test frames {proto.test_frames}, scale {proto.scale:g} of the release (resize {resize:g}), pixels "
             f"{proto.pixels}"]
    if proto.sequence and not src.sequence:
        notes.append(f"the capture's folders do not name its recording: make sure it is {proto.sequence}")
    if resize > 1.0 + 1e-9:
        raise InputError(f"--benchmark {proto.name} scores images at {proto.scale:g} of the release's resolution; "
                         f"these are at {src.release_scale:g}", where=str(src.root),
                         fix=f"ingest the release's images at scale {proto.scale:g} or larger")
    role = proto.role(src.sequence)
    if role != "train":
        lacking = [v for v in proto.test_views if v not in src.camera_names]
        if lacking:
            raise InputError(f"the capture lacks the held-out camera(s) {', '.join(lacking)} of --benchmark "
                             f"{proto.name}", where=str(src.root), fix="add their frames and masks to the capture")
        dropped = [v for v in proto.test_views if v not in cams]
        if dropped:
            raise InputError(f"--views leaves out the held-out camera(s) {', '.join(dropped)} of --benchmark "
                             f"{proto.name}", where="--views", fix=f"add {','.join(dropped)} to --views")
    train_nums = proto.train_frame_numbers() if role != "test" else []
    test_nums = proto.test_frame_numbers() if role != "train" else []
    expected = sorted(set(train_nums) | set(test_nums))
    have = set(available)
    pool = [f for f in expected if f in have]
    frames = select_frames(frames_spec, pool, what="--frames") if frames_spec is not None else pool
    chosen = set(frames)
    train = [f for f in train_nums if f in chosen]
    test = [f for f in test_nums if f in chosen]  # novel_view: training frames too (held-out views)
    for what, got, spec in (("training", train, proto.train_frames), ("test", test, proto.test_frames)):
        if got or role == ("test" if what == "training" else "train"):
            continue
        both = role == "both"
        raise InputError(f"the capture holds none of the {what} frames {spec} of --benchmark {proto.name} "
                         f"(it has {fmt_list(sorted(have))})" if frames_spec is None else
                         f"--frames {frames_spec} keeps none of the {what} frames {spec} of --benchmark "
                         f"{proto.name}", where=str(src.root),
                         fix=f"download frames {f'{proto.train_frames} and {proto.test_frames}' if both else spec} "
                             "(stop exclusive)" if frames_spec is None else
                             "select frames of both the training and the test range" if both else
                             f"select frames of {spec}")
    test_views = [v for v in cams if v in proto.test_views] if role != "train" else []
    train_views = [v for v in cams if v not in test_views
                   and (proto.train_views is None or v in proto.train_views)] if role != "test" else []
    if not train_views and role != "test":
        raise InputError(f"no training camera left under --benchmark {proto.name}", where=str(src.root),
                         fix="ingest the capture's other cameras too")
    if role == "train":
        notes.append(f"{src.sequence} is the training recording of benchmark {proto.name}: ingest "
                     f"{proto.test_sequence} with it too and score with `avatarctl eval THIS --test-project THAT`")
    elif role == "test":
        notes.append(f"{src.sequence} is the test recording of benchmark {proto.name} (nothing to fit here): score "
                     f"the {proto.sequence} project with `avatarctl eval THAT --test-project THIS`")
    partial = []
    if len(frames) < len(expected):
        partial.append(f"frames: {len(frames)} of the protocol's {len(expected)}")
    n_views = len(train_views) + len(test_views)
    if proto.cameras is not None and n_views < proto.cameras:
        partial.append(f"cameras: {n_views} of the protocol's {proto.cameras}")
    elif proto.train_views is not None and len(train_views) < len(proto.train_views) and role != "test":
        partial.append(f"training cameras: {len(train_views)} of the protocol's {len(proto.train_views)}")
    elif views_given and len(cams) < len(src.camera_names):
        partial.append(f"cameras: {len(cams)} of the capture's {len(src.camera_names)} (--views)")
    record = IngestedBenchmark(name=proto.name, dataset=proto.dataset, resize=resize, frames=len(frames),
                               frames_expected=len(expected), train_views=train_views, test_views=test_views,
                               partial=partial, sequence=src.sequence, role=role)
    split = Split(train_frames=train, test_frames=test if proto.split == "novel_pose" else [],
                  train_views=train_views, test_views=test_views)
    kept = cams if role != "test" else test_views
    return BenchmarkPlan(frames=sorted(frames), cams=kept, split=split, resize=resize, record=record, notes=notes)
