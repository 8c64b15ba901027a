"""The train/test split written to ``ingest/split.json``.

From the capture's own ``split.json`` when it has one (restricted to the ingested frames and views), else the
documented default: every view trains except every 4th (views 3, 7, 11, ... in calibration order) which is a test
view; with fewer than 4 views the test views are all views (novel-pose evaluation). The first 2/3 of the frames
(rounded) train, the last 1/3 test. Fit and eval may override it later.
"""

from __future__ import annotations

from avatarctl.errors import InputError
from avatarctl.io.project_io import Split


def default_split(frames: list[int], views: list[str]) -> Split:
    test_views = [v for i, v in enumerate(views) if i % 4 == 3]
    train_views = [v for v in views if v not in test_views]
    if not test_views:
        test_views = list(views)
    n_train = max(1, round(len(frames) * 2 / 3)) if frames else 0
    return Split(train_frames=list(frames[:n_train]), test_frames=list(frames[n_train:]), train_views=train_views,
                 test_views=test_views)


def restrict_split(split: Split, frames: list[int], views: list[str]) -> Split:
    """`split` limited to the ingested `frames` and `views` (order kept)."""
    fs, vs = set(frames), set(views)
    return Split(train_frames=[f for f in split.train_frames if f in fs],
                 test_frames=[f for f in split.test_frames if f in fs],
                 train_views=[v for v in split.train_views if v in vs],
                 test_views=[v for v in split.test_views if v in vs])


def check_split_views(split: Split, cameras: list[str], where: str) -> None:
    """Refuse a capture `split.json` naming a view the capture lacks (a typo there would leave the project without
    the held-out view it asks for). Views the capture has but `--views` left out are dropped later by
    `restrict_split`, quietly."""
    known = set(cameras)
    for key, views in (("test_views", split.test_views), ("train_views", split.train_views)):
        unknown = [v for v in views if v not in known]
        if unknown:
            names = ", ".join(repr(v) for v in unknown)
            raise InputError(f"split.json {key} names {names}, a view the capture lacks", where=where,
                             fix=f"the capture's cameras are: {', '.join(cameras)}; correct split.json")
