"""Reading and writing the ingested capture inside a project directory (cameras, split, frames, masks, fits).

Ingest writes through these functions; fit, render and eval read through them. Paths come from `ProjectPaths`.
Frames are undistorted RGB (uint8, JPEG quality 95), masks undistorted uint8 0/255 PNG, cameras pinhole.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from avatarctl.atomic import write_image, write_json
from avatarctl.body.motion import BodyMotion
from avatarctl.errors import InputError, ProjectError
from avatarctl.evaluate.colour import CameraGains
from avatarctl.project import Project
from avatarctl.geometry.cameras import Camera

JPEG_QUALITY = 95


@dataclass(frozen=True)
class Split:
    """Which frames (capture frame numbers) and views (camera names) are for training and for testing."""

    train_frames: list[int]
    test_frames: list[int]
    train_views: list[str]
    test_views: list[str]

    def to_json(self) -> dict:
        return asdict(self)

    @classmethod
    def from_json(cls, d: dict) -> "Split":
        return cls(train_frames=[int(f) for f in d["train_frames"]], test_frames=[int(f) for f in d["test_frames"]],
                   train_views=[str(v) for v in d["train_views"]], test_views=[str(v) for v in d["test_views"]])


@dataclass(frozen=True)
class IngestedBenchmark:
    """``ingest/benchmark.json``: the named benchmark protocol (`avatarctl.evaluate.benchmarks`) ingest applied, and
    where the project falls short of it (a partial download, narrowed --frames / --views)."""

    name: str  # the protocol's name
    dataset: str  # the capture format it is for
    resize: float  # the scale ingest applied to the capture's images
    frames: int  # frames ingested (train + test)
    frames_expected: int  # frames the protocol names
    train_views: list[str]
    test_views: list[str]
    partial: list[str]  # why the project does not meet the protocol in full (empty: it does)
    sequence: str = ""  # the recording ingested (`CaptureSource.sequence`; "": its folders do not say)
    role: str = "both"  # `BenchmarkProtocol.role`: "both" (train and test frames here), or the "train" / "test"
    # recording of a protocol whose test frames are another recording (`eval --test-project`)

    def to_json(self) -> dict:
        return asdict(self)

    @classmethod
    def from_json(cls, d: dict) -> "IngestedBenchmark":
        older = {"sequence": "", "role": "both"}  # absent from files written before two-recording protocols
        return cls(name=str(d["name"]), dataset=str(d["dataset"]), resize=float(d["resize"]), frames=int(d["frames"]),
                   frames_expected=int(d["frames_expected"]), train_views=[str(v) for v in d["train_views"]],
                   test_views=[str(v) for v in d["test_views"]], partial=[str(p) for p in d["partial"]],
                   **{k: str(d[k]) if k in d else v for k, v in older.items()})


@dataclass(frozen=True)
class ProjectCapture:
    """Everything ingest produced, loaded (images stay on disk and are read lazily)."""

    project: Project
    cameras: dict[str, Camera]  # name -> undistorted pinhole camera
    split: Split
    motion: BodyMotion  # one row per ingested frame
    body_model: str
    body_model_path: str | None
    camera_colour: CameraGains | None = None  # ingest/camera_colour.json; None: one camera, or an older project

    @property
    def frames(self) -> list[int]:
        return [int(f) for f in self.motion.frame_index]

    def image(self, cam: str, frame: int) -> np.ndarray:
        return read_frame(self.project, cam, frame)

    def mask(self, cam: str, frame: int) -> np.ndarray:
        return read_mask(self.project, cam, frame)


def save_cameras(path: Path, cameras: list[Camera]) -> None:
    write_json(path, {"cameras": [c.to_json() for c in cameras]})


def _read_ingest_json(path: Path, what: str, build):
    """`build(json.loads(path))` for an ingest output, with a one-line `ProjectError` when it is missing, cut off,
    not UTF-8 or has the wrong content."""
    path = Path(path)
    if not path.is_file():
        raise ProjectError(f"{what} file missing", where=str(path), fix="re-run `avatarctl ingest`")
    try:
        return build(json.loads(path.read_bytes().decode("utf-8")))
    except (UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError, ValueError) as e:
        detail = " ".join(str(e).split())[:160]
        raise ProjectError(f"{what} file is damaged ({type(e).__name__}: {detail})", where=str(path),
                           fix="re-run `avatarctl ingest` into a new project") from None


def load_cameras(path: Path) -> dict[str, Camera]:
    return _read_ingest_json(path, "cameras", lambda d: {c["name"]: Camera.from_json(c) for c in d["cameras"]})


def save_split(path: Path, split: Split) -> None:
    write_json(path, split.to_json())


def load_split(path: Path) -> Split:
    return _read_ingest_json(path, "split", Split.from_json)


def save_benchmark(path: Path, record: IngestedBenchmark) -> None:
    write_json(path, record.to_json())


def load_benchmark(project: Project) -> IngestedBenchmark | None:
    """The project's ``ingest/benchmark.json``, or None when ingest applied no benchmark protocol."""
    path = project.paths.benchmark
    return _read_ingest_json(path, "benchmark", IngestedBenchmark.from_json) if path.is_file() else None


def save_camera_colour(path: Path, gains: CameraGains) -> None:
    write_json(path, gains.to_json())


def load_camera_colour(project: Project) -> CameraGains | None:
    """The project's ``ingest/camera_colour.json``, or None (one camera; a project ingested before issue 51)."""
    path = project.paths.camera_colour
    return _read_ingest_json(path, "camera colour", CameraGains.from_json) if path.is_file() else None


def write_frame(project: Project, cam: str, frame: int, rgb: np.ndarray) -> Path:
    """Write an undistorted RGB uint8 [H, W, 3] frame atomically."""
    import cv2

    dest = project.paths.frame(cam, frame)
    return write_image(dest, cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])


def write_mask(project: Project, cam: str, frame: int, mask: np.ndarray) -> Path:
    """Write a foreground mask (bool or uint8, [H, W]) as 0/255 PNG atomically."""
    import cv2

    return write_image(project.paths.mask(cam, frame), (np.asarray(mask) > 0).astype(np.uint8) * 255)


def _read_image(path: Path, flag: int, message: str) -> np.ndarray:
    """cv2.imread that raises an actionable ProjectError for a missing or unreadable project image."""
    import cv2

    img = cv2.imread(str(path), flag)
    if img is None:
        raise ProjectError(message, where=str(path), fix="re-run `avatarctl ingest`")
    return img


def read_frame(project: Project, cam: str, frame: int) -> np.ndarray:
    """Undistorted RGB uint8 [H, W, 3]."""
    import cv2

    img = _read_image(project.paths.frame(cam, frame), cv2.IMREAD_COLOR,
                      f"frame image missing or unreadable: camera {cam}, frame {frame}")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def read_mask(project: Project, cam: str, frame: int) -> np.ndarray:
    """Foreground mask, bool [H, W]."""
    import cv2

    m = _read_image(project.paths.mask(cam, frame), cv2.IMREAD_GRAYSCALE,
                    f"mask missing or unreadable: camera {cam}, frame {frame}")
    return m > 127


def load_project_capture(project: Project) -> ProjectCapture:
    """Load what ingest wrote (checks that ingest ran and its outputs exist)."""
    project.require("ingest")
    p = project.paths
    if not p.body.is_file():
        raise ProjectError("body fits missing", where=str(p.body), fix="re-run `avatarctl ingest`")
    try:
        motion = BodyMotion.load(p.body)
    except InputError as e:
        raise ProjectError(e.what, where=e.where, fix="re-run `avatarctl ingest` into a new project") from None
    bm = project.manifest.body_model
    cameras, split = load_cameras(p.cameras), load_split(p.split)
    _check_images_present(project, list(cameras), [int(f) for f in motion.frame_index])
    return ProjectCapture(project=project, cameras=cameras, split=split, motion=motion, body_model=bm.name,
                          body_model_path=bm.path, camera_colour=load_camera_colour(project))


def _check_images_present(project: Project, cams: list[str], frames: list[int]) -> None:
    """Every (camera, frame) ingest wrote still has its frame and mask file (a stat each; pixels stay lazy), so a
    stage fails before its first step, not when the sampler happens to reach a deleted file."""
    p = project.paths
    for cam in cams:
        for f in frames:
            for path in (p.frame(cam, f), p.mask(cam, f)):
                if not path.is_file() or path.stat().st_size == 0:
                    raise ProjectError(f"ingest output missing or empty: camera {cam}, frame {f}", where=str(path),
                                       fix="restore the file, or re-run `avatarctl ingest` into a new project")
