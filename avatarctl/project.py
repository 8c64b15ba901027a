"""The project directory contract: every path a stage reads or writes, and the manifest `project.json`.

Layout (see docs/project_dir.md)::

    PROJECT/
      project.json                      manifest: schema_version, body model, source capture, stage records
      ingest/cameras.json               undistorted pinhole cameras (OpenCV, world->camera, metres)
      ingest/frames/<cam>/<frame:06d>.jpg   undistorted RGB frames
      ingest/masks/<cam>/<frame:06d>.png    undistorted foreground masks (0 / 255)
      ingest/body.npz                   body-model fits, one row per frame (see avatarctl.body.motion)
      ingest/split.json                 train/test frames and views
      ingest/benchmark.json             the named benchmark protocol ingest applied (`ingest --benchmark`), if any
      ingest/camera_colour.json         each camera's colour gains from the body's colours across cameras (2+ cameras)
      ingest/contact_sheet.png          frames with the posed body overlaid, for a person to check
      ingest/keypoints.npz              the person detector's 2D keypoints per view (when ingest detected people)
      fit/config.json                   resolved fit config
      fit/log.jsonl                     one JSON record per logged step
      fit/checkpoints/step_<step:08d>.pt, fit/checkpoints/latest.pt
      render/<name>/...                 frames/*.png, video.mp4, config.json
      eval/<name>/...                   metrics.json, per_frame.csv, sheet.png
      export/<name>/...                 avatar.glb (skinned, animated), meshes/<frame:06d>.{glb,ply,obj}, export.json

Only this module knows these names. Writes go through `avatarctl.atomic`; the outputs' locks are files
`.<output>.lock` beside them (`avatarctl.lock`), present only while a command writes.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import os
import re
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from avatarctl import __version__
from avatarctl.atomic import write_json
from avatarctl.errors import ProjectError
from avatarctl.lock import hold

SCHEMA_VERSION = 1
STAGES = ("ingest", "fit", "render", "eval", "export")
_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$")


def now_iso() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def check_name(name: str, what: str = "name") -> str:
    """Render/eval output names become folder names: keep them simple."""
    if not _NAME_RE.match(name):
        raise ProjectError(f"invalid {what} {name!r}", fix="use letters, digits, '.', '_' or '-' (max 64 chars)")
    return name


@dataclass(frozen=True)
class ProjectPaths:
    """Every path inside a project directory."""

    root: Path

    @property
    def manifest(self) -> Path:
        return self.root / "project.json"

    # ---- ingest -------------------------------------------------------------------------------------------
    @property
    def ingest(self) -> Path:
        return self.root / "ingest"

    @property
    def cameras(self) -> Path:
        return self.ingest / "cameras.json"

    @property
    def body(self) -> Path:
        return self.ingest / "body.npz"

    @property
    def split(self) -> Path:
        return self.ingest / "split.json"

    @property
    def benchmark(self) -> Path:
        return self.ingest / "benchmark.json"

    @property
    def camera_colour(self) -> Path:
        return self.ingest / "camera_colour.json"

    @property
    def keypoints(self) -> Path:
        return self.ingest / "keypoints.npz"

    @property
    def ingest_contact_sheet(self) -> Path:
        return self.ingest / "contact_sheet.png"

    def frame(self, cam: str, frame: int) -> Path:
        return self.ingest / "frames" / cam / f"{frame:06d}.jpg"

    def mask(self, cam: str, frame: int) -> Path:
        return self.ingest / "masks" / cam / f"{frame:06d}.png"

    # ---- fit ----------------------------------------------------------------------------------------------
    @property
    def fit(self) -> Path:
        return self.root / "fit"

    @property
    def fit_config(self) -> Path:
        return self.fit / "config.json"

    @property
    def fit_log(self) -> Path:
        return self.fit / "log.jsonl"

    @property
    def checkpoints(self) -> Path:
        return self.fit / "checkpoints"

    def checkpoint(self, step: int) -> Path:
        return self.checkpoints / f"step_{step:08d}.pt"

    @property
    def latest_checkpoint(self) -> Path:
        return self.checkpoints / "latest.pt"

    # ---- render / eval ------------------------------------------------------------------------------------
    def render(self, name: str) -> Path:
        return self.root / "render" / check_name(name, "render name")

    def eval(self, name: str) -> Path:
        return self.root / "eval" / check_name(name, "eval name")

    def export(self, name: str) -> Path:
        return self.root / "export" / check_name(name, "export name")


@dataclass
class StageRecord:
    """One run of one stage."""

    stage: str
    started: str
    finished: str
    version: str
    config: dict[str, Any]
    outputs: list[str]
    summary: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class BodyModelRef:
    """Which body model a project's fits are for (`project.json` "body_model")."""

    name: str  # "anny" | "smpl" | "smplx" | "toy"
    path: str | None = None  # the user's SMPL / SMPL-X model file; None for file-free models

    def to_json(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> "BodyModelRef":
        return cls(name=str(d["name"]), path=None if d["path"] is None else str(d["path"]))


@dataclass(frozen=True)
class SourceRef:
    """The capture a project was ingested from (`project.json` "source")."""

    path: str  # capture folder, absolute
    format: str  # easymocap | zju | thuman4 | peoplesnapshot | colmap | synthetic (tests)
    sha256: str  # of the capture's file tree (`hash_tree`)
    files: int  # files hashed

    def to_json(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> "SourceRef":
        return cls(path=str(d["path"]), format=str(d["format"]), sha256=str(d["sha256"]), files=int(d["files"]))


@dataclass
class Manifest:
    """`project.json`."""

    schema_version: int
    body_model: BodyModelRef
    source: SourceRef
    created: str
    stages: list[StageRecord] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_json(cls, d: dict[str, Any], where: Path) -> "Manifest":
        try:
            return cls(
                schema_version=int(d["schema_version"]),
                body_model=BodyModelRef.from_json(d["body_model"]),
                source=SourceRef.from_json(d["source"]),
                created=str(d["created"]),
                stages=[StageRecord(**s) for s in d["stages"]],
            )
        except (KeyError, TypeError, ValueError) as e:
            raise ProjectError(f"malformed project manifest ({e})", where=str(where),
                               fix="re-create the project with `avatarctl ingest`") from None


class Project:
    """A project directory: its paths and its manifest."""

    def __init__(self, root: Path, manifest: Manifest):
        self.root = Path(root)
        self.paths = ProjectPaths(self.root)
        self.manifest = manifest

    # ---- create / open -------------------------------------------------------------------------------------
    @classmethod
    def create(cls, root: str | os.PathLike, body_model: BodyModelRef, source: SourceRef) -> "Project":
        """Write a fresh manifest into `root` (which must not already hold a project)."""
        root = Path(root)
        if (root / "project.json").exists():
            raise ProjectError("a project already exists here", where=str(root),
                               fix="choose a new PROJECT directory or delete this one")
        proj = cls(root, Manifest(SCHEMA_VERSION, body_model, source, now_iso()))
        proj.save()
        return proj

    @classmethod
    def open(cls, root: str | os.PathLike) -> "Project":
        root = Path(root)
        return cls(root, _read_manifest(root))

    def save(self) -> None:
        write_json(self.paths.manifest, self.manifest.to_json())

    # ---- stage records -------------------------------------------------------------------------------------
    def record(self, stage: str, config: dict[str, Any], outputs: list[str | Path], started: str,
               summary: dict[str, Any] | None = None) -> StageRecord:
        """Append a stage record and save the manifest atomically. Output paths are stored relative to root.

        Read-modify-write under the manifest's lock (`avatarctl.lock`, waited for: it is held for milliseconds),
        the manifest read again first, so that commands running together (a fit and a render) keep each other's
        records."""
        if stage not in STAGES:
            raise ValueError(f"unknown stage {stage!r}; expected one of {STAGES}")
        rel = [_relative_to_root(Path(p), self.root) for p in outputs]
        rec = StageRecord(stage=stage, started=started, finished=now_iso(), version=__version__,
                          config=config, outputs=rel, summary=summary or {})
        with hold(self.paths.manifest, f"{stage} (recording in project.json)", wait=True):
            if self.paths.manifest.is_file():
                self.manifest = _read_manifest(self.root)
            self.manifest.stages.append(rec)
            self.save()
        return rec

    def last(self, stage: str) -> StageRecord | None:
        for rec in reversed(self.manifest.stages):
            if rec.stage == stage:
                return rec
        return None

    def require(self, stage: str) -> StageRecord:
        """The last record of `stage`, checking that every output it lists is still on disk."""
        rec = self.last(stage)
        hint = {"ingest": "run `avatarctl ingest CAPTURE PROJECT`", "fit": f"run `avatarctl fit {self.root}`",
                "render": f"run `avatarctl render {self.root}`", "eval": f"run `avatarctl eval {self.root}`",
                "export": f"run `avatarctl export {self.root}`"}[stage]
        if rec is None:
            raise ProjectError(f"project has no {stage} output yet", where=str(self.root), fix=hint)
        for out in rec.outputs:
            if not (self.root / out).exists():
                raise ProjectError(f"{stage} output is missing: {out}", where=str(self.root),
                                   fix=f"{hint} again")
        return rec


def _read_manifest(root: Path) -> Manifest:
    mpath = root / "project.json"
    if not mpath.is_file():
        raise ProjectError("not an avatarctl project (no project.json)", where=str(root),
                           fix="create one with `avatarctl ingest CAPTURE PROJECT`")
    try:
        data = json.loads(mpath.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise ProjectError(f"cannot read project manifest ({e})", where=str(mpath),
                           fix="re-create the project with `avatarctl ingest`") from None
    version = data.get("schema_version")
    if version != SCHEMA_VERSION:
        raise ProjectError(f"unknown project schema_version {version!r} (this avatarctl {__version__} reads "
                           f"{SCHEMA_VERSION})", where=str(mpath),
                           fix="use the avatarctl version that wrote it, or re-run `avatarctl ingest`")
    return Manifest.from_json(data, mpath)


def _relative_to_root(p: Path, root: Path) -> str:
    """An output path as stored in the manifest: relative to the project root. Paths built from `ProjectPaths`
    start with `root` even when `root` itself is relative (e.g. `avatarctl render proj`); other relative paths are
    taken as already relative to the root."""
    try:
        return p.relative_to(root).as_posix()
    except ValueError:
        return os.path.relpath(p, root) if p.is_absolute() else str(p)


def sha256_file(path: str | os.PathLike, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def hash_tree(root: str | os.PathLike) -> tuple[str, int]:
    """Content hash of a directory tree: sha256 over sorted (relative path, file sha256). Returns (hex, files)."""
    root = Path(root)
    h = hashlib.sha256()
    n = 0
    for p in sorted(q for q in root.rglob("*") if q.is_file()):
        h.update(p.relative_to(root).as_posix().encode())
        h.update(b"\0")
        h.update(sha256_file(p).encode())
        n += 1
    return h.hexdigest(), n
