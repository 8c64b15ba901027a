"""Issue 15: every bad input is refused cleanly, through the CLI, in-process.

Table-driven: each `Fault` corrupts a copy of a small fixture (the toy-body capture, its ingested project, or the
project after a 4-step fit), runs one CLI command on it, and expects

- exit code 2 (an `AvatarError` mapped by the CLI, not a crash: a bug exits 70 with "internal error"); 74 for a
  refused write, 75 for an output another command is writing (issue 32: its lock is held during the command),
- exactly one line on stderr, starting with "error:", containing the fault's message fragment, no traceback,
- the source untouched and nothing half-written: the content hash of the whole capture AND project trees (hidden
  temporary files included) is the same before and after the command, and an ingest leaves no PROJECT behind.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import pickle
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import pytest
from fixtures.toy_capture import make_toy_project
from typer.testing import CliRunner

from avatarctl.cli.app import app
from avatarctl.lock import hold
from avatarctl.project import hash_tree

CAMS = ("cam00", "cam01", "cam02", "cam03")


# ---- fixtures: one capture, its project, the project fitted for 4 steps (built once per module) ------------------
@pytest.fixture(scope="module")
def base(tmp_path_factory) -> dict[str, Path]:
    from avatarctl.stages import fit
    from avatarctl.stages.fit import FitRequest

    root = tmp_path_factory.mktemp("faults_base")
    cap, proj = make_toy_project(root)
    fitted = root / "fitted"
    shutil.copytree(proj, fitted)
    fit.run(fitted, FitRequest(preset="micro", iters=2, overrides=("val_every=0",), device="cpu"),
            handle_sigint=False)
    return {"capture": cap, "project": proj, "fitted": fitted}


@pytest.fixture(scope="module")
def person_frames(tmp_path_factory) -> dict[str, np.ndarray]:
    """Frames of a synthetic person (the `phone` preset at 96x160: big enough for MediaPipe) and the empty scene."""
    import cv2

    from avatarctl.synth import SynthConfig, synthesize

    out = tmp_path_factory.mktemp("faults_person") / "phone"
    synthesize(out, SynthConfig.preset("phone", size=160, width=96, train_frames=3, test_frames=1, supersample=1))
    cap = out / "gt" / "capture"
    person = [cv2.imread(str(p))[..., ::-1] for p in sorted((cap / "images" / "cam00").iterdir())]
    return {"person": np.stack(person), "empty": cv2.imread(str(cap / "background" / "cam00.jpg"))[..., ::-1]}


# ---- corruption helpers -------------------------------------------------------------------------------------------
def _rewrite_calib(path: Path, change: dict[str, object]) -> None:
    """Rewrite an OpenCV FileStorage YAML file with some top-level entries replaced (None: removed)."""
    import cv2

    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    root = fs.root()
    entries: dict[str, object] = {}
    for key in root.keys():
        node = fs.getNode(key)
        if key == "names":
            entries[key] = [node.at(i).string() for i in range(node.size())]
        elif node.isInt():
            entries[key] = int(node.real())
        else:
            entries[key] = node.mat()
    fs.release()
    entries.update(change)
    out = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for key, value in entries.items():
        if value is None:
            continue
        if key == "names":
            out.startWriteStruct("names", cv2.FileNode_SEQ)
            for n in value:
                out.write("", n)
            out.endWriteStruct()
        else:
            out.write(key, value)
    out.release()


def _mat(path: Path, key: str) -> np.ndarray:
    import cv2

    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    m = fs.getNode(key).mat()
    fs.release()
    return m


def _set_entry(fname: str, key: str, fn: Callable[[np.ndarray], object]) -> Callable[[Path], None]:
    def corrupt(cap: Path) -> None:
        _rewrite_calib(cap / fname, {key: fn(_mat(cap / fname, key))})
    return corrupt


def _with(arr: np.ndarray, index: tuple, value: float) -> np.ndarray:
    arr = arr.copy()
    arr[index] = value
    return arr


def _truncate(rel: str, keep: float = 0.5) -> Callable[[Path], None]:
    def corrupt(root: Path) -> None:
        p = root / rel
        data = p.read_bytes()
        p.write_bytes(data[: int(len(data) * keep)])
    return corrupt


def _write(rel: str, data: bytes) -> Callable[[Path], None]:
    def corrupt(root: Path) -> None:
        (root / rel).write_bytes(data)
    return corrupt


def _remove(rel: str) -> Callable[[Path], None]:
    return lambda root: (root / rel).unlink()


def _image(rel: str, fn: Callable[[np.ndarray], np.ndarray]) -> Callable[[Path], None]:
    def corrupt(root: Path) -> None:
        import cv2

        p = root / rel
        cv2.imwrite(str(p), fn(cv2.imread(str(p), cv2.IMREAD_UNCHANGED)))
    return corrupt


def _motion(change: Callable[[dict[str, np.ndarray]], None], rel: str = "motion.npz") -> Callable[[Path], None]:
    def corrupt(root: Path) -> None:
        p = root / rel
        with np.load(p, allow_pickle=False) as z:
            d = {k: z[k] for k in z.files}
        change(d)
        with open(p, "wb") as fh:
            np.savez(fh, **d)
    return corrupt


def _json(rel: str, change: Callable[[dict], None]) -> Callable[[Path], None]:
    def corrupt(root: Path) -> None:
        p = root / rel
        d = json.loads(p.read_text())
        change(d)
        p.write_text(json.dumps(d))
    return corrupt


def _put(d: dict, key: str, value) -> None:
    d[key] = value


class _Payload:
    """A pickle whose loading runs `touch <marker>` (what a malicious file would do with os.system)."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        import os

        return os.system, (f"touch {self.marker}",)


def _malicious(rel: str, npy: bool = False) -> Callable[[Path], None]:
    def corrupt(root: Path) -> None:
        marker = root.parent / "PWNED"
        if npy:
            np.save(root / rel, np.array(_Payload(marker), dtype=object), allow_pickle=True)
        else:
            (root / rel).write_bytes(pickle.dumps({"camera_f": _Payload(marker)}, protocol=2))
    return corrupt


def _zju_annots(root: Path) -> Path:
    """A well-formed annots.npy (one camera) in `root`; returns `root`."""
    cams = {"K": [np.eye(3)], "D": [np.zeros((5, 1))], "R": [np.eye(3)], "T": [np.zeros((3, 1))]}
    np.save(root / "annots.npy", np.array({"cams": cams, "ims": [{"ims": ["cam00/000000.jpg"]}]}, dtype=object),
            allow_pickle=True)
    return root


def _colmap_garbage(root: Path) -> None:
    (root / "sparse" / "0").mkdir(parents=True)
    (root / "sparse" / "0" / "cameras.txt").write_bytes(b"1 PINHOLE 32 \xff garbage\n")
    (root / "sparse" / "0" / "images.txt").write_text("not an images file\n")
    (root / "sparse" / "0" / "points3D.txt").write_text("")


def _amass(rel: str, width: int) -> Callable[[Path], None]:
    def corrupt(root: Path) -> None:
        n = 3
        np.savez(root / rel, poses=np.zeros((n, width), np.float32), trans=np.zeros((n, 3), np.float32),
                 betas=np.zeros(16, np.float32), mocap_framerate=np.array(30.0))
    return corrupt


def _toy_motion_file(rel: str, change: Callable[[dict[str, np.ndarray]], None]) -> Callable[[Path], None]:
    """A copy of the project's ingest/body.npz at `rel`, changed."""
    def corrupt(root: Path) -> None:
        shutil.copy(root / "ingest" / "body.npz", root.parent / rel)
        _motion(change, rel="../" + rel)(root)
    return corrupt


def _video(frames: Callable[[dict], list[np.ndarray]], name: str = "clip.mp4") -> Callable[[Path, dict], None]:
    """Write `name` from `frames(person_frames)` (RGB uint8 [H, W, 3] each) into the copied folder."""
    def corrupt(root: Path, person: dict) -> None:
        import imageio_ffmpeg

        fr = frames(person)
        gen = imageio_ffmpeg.write_frames(str(root / name), (fr[0].shape[1], fr[0].shape[0]), fps=10, quality=9,
                                          macro_block_size=1)
        gen.send(None)
        for f in fr:
            gen.send(np.ascontiguousarray(f))
        gen.close()
    return corrupt


def _plain(n: int) -> Callable[[dict], list[np.ndarray]]:
    """n frames of a smooth random texture: no person."""
    rng = np.random.default_rng(0)
    img = np.kron(rng.integers(40, 220, (10, 6, 3)), np.ones((16, 16, 1))).astype(np.uint8)
    return lambda person: [img] * n


def _no_space(monkeypatch) -> None:
    """The disk is full: every file rename that would publish a finished output fails with ENOSPC (what the
    temporary-file writes of `avatarctl.atomic` end with; the writes before it are in the page cache)."""
    import os

    def replace(src, dst):  # noqa: ARG001
        raise OSError(errno.ENOSPC, "No space left on device", str(dst))

    monkeypatch.setattr(os, "replace", replace)


def _read_only(monkeypatch) -> None:
    """The output file system is read-only (we run as root in CI, so chmod would not stop us: simulate EROFS)."""
    import avatarctl.atomic as atomic

    def mkstemp(*a, dir=None, **k):  # noqa: ARG001, A002
        raise OSError(errno.EROFS, "Read-only file system", str(dir))

    monkeypatch.setattr(atomic.tempfile, "mkstemp", mkstemp)
    monkeypatch.setattr(atomic.tempfile, "mkdtemp", mkstemp)


# ---- the table ------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Fault:
    name: str
    on: str  # "capture" (ingest) | "project" (ingested, no fit) | "fitted" (ingested + 2-step fit) | "video" (an
    #          empty folder: ingest of the clip.mp4 that `corrupt` writes into it)
    corrupt: Callable[[Path], None] | None  # applied to the copied `on` tree (video: (folder, person_frames))
    args: Callable[[Path, Path], list[str]]  # (source, out) -> CLI args; out = where ingest writes
    expect: str  # fragment of the one-line message
    patch: Callable[[pytest.MonkeyPatch], None] | None = None  # environment faults (disk)
    marker: bool = field(default=False)  # a malicious pickle: its payload must never run
    code: int = 2  # exit code: 2 an AvatarError (bad input / project), 74 the system refused a write, 75 busy
    busy: tuple[Callable[[Path, Path], Path], str] | None = None  # an output ((source, out) -> path) and the command
    #                                                                 holding its lock during this one
    needs: str | None = None  # a module the fault needs (skipped without it: MediaPipe, the capture extra)


def busy(rel: str | None, command: str = "fit") -> dict:
    """Fault fields for an output (`rel` in the source tree; None: ingest's PROJECT) that `command` is writing: its
    lock is held during the command (in this process, through another file description: to flock, another
    process; tests/test_lock.py holds them from real other processes)."""
    return {"busy": ((lambda src, out: src / rel) if rel else (lambda src, out: out), command), "code": 75,
            "expect": f"is being written by `{command}` (pid {os.getpid()}"}


def ingest(*extra: str) -> Callable[[Path, Path], list[str]]:
    return lambda src, out: ["ingest", str(src), str(out), "--no-contact-sheet", *extra]


def video(*extra: str) -> Callable[[Path, Path], list[str]]:
    return lambda src, out: ["ingest", str(src / "clip.mp4"), str(out), "--no-contact-sheet", *extra]


def fit(*extra: str) -> Callable[[Path, Path], list[str]]:
    return lambda src, out: ["fit", str(src), "--preset", "micro", "--iters", "1", "--device", "cpu", *extra]


def resume(*extra: str) -> Callable[[Path, Path], list[str]]:
    return lambda src, out: ["fit", str(src), "--resume", "--device", "cpu", *extra]


def render(*extra: str) -> Callable[[Path, Path], list[str]]:
    return lambda src, out: ["render", str(src), "--device", "cpu", "--frames", "0", "--views", "cam00", *extra]


def poses(rel: str) -> Callable[[Path, Path], list[str]]:
    return lambda src, out: ["render", str(src), "--device", "cpu", "--poses", str(src / rel)]


def evaluate(*extra: str) -> Callable[[Path, Path], list[str]]:
    return lambda src, out: ["eval", str(src), "--device", "cpu", "--sheet", "0", *extra]


INTRI, EXTRI = "intri.yml", "extri.yml"
IMG0, MASK0 = "images/cam01/000002.jpg", "masks/cam01/000002.png"

FAULTS = [
    # -- calibration
    Fault("intri_truncated", "capture", _truncate(INTRI), ingest(), "intri.yml"),
    Fault("intri_empty", "capture", _write(INTRI, b""), ingest(), "intri.yml"),
    Fault("intri_not_utf8", "capture", lambda c: (c / INTRI).write_bytes(b"%YAML:1.0\n\xff\xfe\x00names: [\x9c]\n"),
          ingest(), "intri.yml"),
    Fault("extri_truncated", "capture", _truncate(EXTRI, 0.3), ingest(), "extri.yml"),
    Fault("camera_in_intri_not_extri", "capture",
          lambda c: _rewrite_calib(c / EXTRI, {"names": list(CAMS[:3]), "R_cam03": None, "Rot_cam03": None,
                                               "T_cam03": None}), ingest(), "not in extri.yml"),
    Fault("K_nan", "capture", _set_entry(INTRI, "K_cam01", lambda K: _with(K, (0, 0), np.nan)), ingest(),
          "non-finite"),
    Fault("R_inf", "capture", _set_entry(EXTRI, "Rot_cam02", lambda R: _with(R, (1, 1), np.inf)), ingest(),
          "non-finite"),
    Fault("T_nan", "capture", _set_entry(EXTRI, "T_cam00", lambda T: _with(T, (2, 0), np.nan)), ingest(),
          "non-finite"),
    Fault("R_not_a_rotation", "capture", _set_entry(EXTRI, "Rot_cam01", lambda R: R * 2.0), ingest(),
          "not a rotation"),
    Fault("dist_wrong_length", "capture", _set_entry(INTRI, "dist_cam00", lambda d: np.zeros((1, 3))), ingest(),
          "distortion"),
    Fault("calibration_in_millimetres", "capture", _set_entry(EXTRI, "T_cam01", lambda T: T * 1000.0), ingest(),
          "millimetres"),
    # -- images and masks
    Fault("image_other_size", "capture", _image(IMG0, lambda im: np.zeros((48, 40, 3), np.uint8)), ingest(),
          "calibrated for 32x32"),
    Fault("image_missing", "capture", _remove(IMG0), ingest(), "frame-count mismatch"),
    Fault("image_corrupt", "capture", _write(IMG0, b"\xff\xd8\xff\xe0 not really a jpeg"), ingest(),
          "unreadable or corrupt"),
    Fault("image_zero_bytes", "capture", _write(IMG0, b""), ingest(), "unreadable or corrupt"),
    Fault("mask_empty", "capture", _image(MASK0, lambda m: np.zeros_like(m)), ingest(), "empty mask"),
    Fault("mask_all_foreground", "capture", _image(MASK0, lambda m: np.full_like(m, 255)), ingest(),
          "whole image"),
    Fault("mask_wrong_size", "capture", _image(MASK0, lambda m: np.full((16, 16), 255, np.uint8)), ingest(),
          "calibrated for 32x32"),
    # -- body fits
    Fault("fits_nan", "capture", _motion(lambda d: d["body_pose"].__setitem__((1, 0), np.nan)), ingest(),
          "non-finite"),
    Fault("fits_wrong_shape", "capture", _motion(lambda d: _put(d, "body_pose", np.zeros((4, 7), np.float32))),
          ingest(), "body_pose"),
    Fault("fits_in_millimetres", "capture", _motion(lambda d: _put(d, "transl", (d["transl"] + 0.9) * 1000.0)),
          ingest(), "millimetres"),
    Fault("fits_fewer_frames_than_images", "capture",
          _motion(lambda d: [_put(d, k, d[k][:2]) for k in ("frame_index", "global_orient", "body_pose", "transl")]),
          ingest(), "frame-count mismatch"),
    Fault("fits_unknown_body_model", "capture", _motion(lambda d: _put(d, "body_model", np.array("smpl-h"))),
          ingest(), "body model"),
    # -- options
    Fault("ingest_frame_that_does_not_exist", "capture", None, ingest("--frames", "7,9"), "frame"),
    Fault("ingest_resize_out_of_range", "capture", None, ingest("--resize", "0"), "out of range"),
    Fault("ingest_unknown_view", "capture", None, ingest("--views", "cam09"), "unknown cameras"),
    Fault("split_names_a_view_the_capture_lacks", "capture",
          _json("split.json", lambda d: _put(d, "test_views", ["zz99"])), ingest(), "test_views names 'zz99', a view the capture lacks"),
    # -- untrusted pickles (the payload must never run)
    Fault("zju_annots_malicious_pickle", "capture", _malicious("annots.npy", npy=True), ingest("--format", "zju"),
          "not allowed", marker=True),
    Fault("peoplesnapshot_camera_malicious_pickle", "capture", _malicious("camera.pkl"),
          ingest("--format", "peoplesnapshot"), "not allowed", marker=True),
    # -- other capture formats (calibration read first, so a copy of the toy capture with the marker file will do)
    Fault("thuman4_calibration_truncated", "capture", _write("calibration.json", b'{"cam00": {"K": [1, 0,'),
          ingest("--format", "thuman4"), "calibration.json"),
    Fault("thuman4_calibration_not_utf8", "capture", _write("calibration.json", b'{"cam\xff\xfe": 1}'),
          ingest("--format", "thuman4"), "calibration.json"),
    Fault("zju_annots_truncated", "capture", lambda c: _truncate("annots.npy", 0.6)(_zju_annots(c)),
          ingest("--format", "zju"), "annots.npy"),
    Fault("peoplesnapshot_camera_truncated", "capture",
          lambda c: _write("camera.pkl", pickle.dumps({"camera_f": [50.0, 50.0], "width": 32})[:20])(c),
          ingest("--format", "peoplesnapshot"), "camera.pkl"),
    Fault("colmap_model_garbage", "capture", _colmap_garbage, ingest("--format", "colmap"), "COLMAP"),
    # -- one phone video (issue 31); "video" is an empty folder the fault writes clip.mp4 into, from frames of a
    #    synthetic person (`person_frames`)
    Fault("video_too_short", "video", _video(_plain(4)), video(), "video too short"),
    Fault("video_no_person", "video", _video(_plain(12)), video(), "no person found", needs="mediapipe"),
    Fault("video_person_out_of_frame_most_of_the_time", "video",
          _video(lambda p: [p["empty"]] * 9 + list(p["person"][:3])), video(), "out of frame", needs="mediapipe"),
    Fault("video_several_people", "video",
          _video(lambda p: [np.concatenate([f, f[:, ::-1]], axis=1) for f in p["person"]] * 3), video(),
          "several people", needs="mediapipe"),
    Fault("video_camera_moves", "video",
          _video(lambda p: [np.roll(p["person"][k % 4], 8 * k - 48, axis=1) for k in range(12)]), video(),
          "the camera moves", needs="mediapipe"),
    Fault("video_height_out_of_range", "video", _video(_plain(12)), video("--height", "17.5"), "--height"),
    Fault("focal_px_for_a_calibrated_capture", "capture", None, ingest("--focal-px", "500"), "for one video"),
    # -- project
    Fault("project_newer_schema", "project", _json("project.json", lambda d: _put(d, "schema_version", 99)), fit(),
          "schema_version 99"),
    Fault("project_manifest_truncated", "project", _truncate("project.json"), fit(), "project manifest"),
    Fault("cameras_json_truncated", "project", _truncate("ingest/cameras.json"), fit(), "cameras.json"),
    Fault("project_frame_missing", "project", _remove("ingest/frames/cam00/000001.jpg"), fit(), "ingest output"),
    Fault("fit_config_key_typo", "project", None, fit("--set", "itres=5"), "itres"),
    Fault("fit_value_out_of_range", "project", None, fit("--set", "lr=-1"), "lr"),
    Fault("fit_no_training_views", "project", _json("ingest/split.json", lambda d: _put(d, "train_views", [])),
          fit(), "no training"),
    Fault("fit_resume_without_checkpoint", "project", None, resume(), "checkpoint not found"),
    Fault("fit_resume_other_config", "fitted", None, resume("--set", "lr=0.5"), "cannot change a fit being resumed"),
    Fault("fit_again_without_fresh", "fitted", None, fit(), "already has a fit"),
    Fault("checkpoint_truncated", "fitted", _truncate("fit/checkpoints/latest.pt"), render(),
          "cannot read fit checkpoint"),
    Fault("checkpoint_empty", "fitted", _write("fit/checkpoints/latest.pt", b""), evaluate(),
          "cannot read fit checkpoint"),
    Fault("checkpoint_malicious_pickle", "fitted", _malicious("fit/checkpoints/latest.pt"), render(),
          "cannot read fit checkpoint", marker=True),
    # -- render / eval
    Fault("render_frame_that_does_not_exist", "fitted", None, render("--frames", "99"), "99"),
    Fault("render_unknown_view", "fitted", None, render("--views", "cam09"), "cam09"),
    Fault("render_resolution_out_of_range", "fitted", None, render("--resolution", "0"), "resolution"),
    Fault("render_motion_other_body_model", "fitted", _amass("amass.npz", 72), poses("amass.npz"),
          "cannot retarget motion onto the 'toy' body model"),
    Fault("render_motion_unknown_keys", "fitted", lambda p: np.savez(p / "motion.npz", qpos=np.zeros((3, 7))),
          poses("motion.npz"), "unrecognised motion file"),
    Fault("render_motion_nan", "fitted",
          _motion(lambda d: d["body_pose"].__setitem__((0, 0), np.nan), rel="ingest/body.npz"), render(),
          "non-finite"),
    Fault("eval_no_held_out_views", "fitted", _json("ingest/split.json", lambda d: _put(d, "test_views", [])),
          evaluate("--split", "novel_view"), "no views for novel_view"),
    Fault("eval_frame_that_does_not_exist", "fitted", None, evaluate("--frames", "42"), "42"),
    # -- the output disk
    Fault("ingest_disk_full", "capture", None, ingest(), "No space left", patch=_no_space, code=74),
    Fault("render_disk_full", "fitted", None, render(), "No space left", patch=_no_space, code=74),
    Fault("fit_resume_disk_full", "fitted", None, resume("--iters", "3"), "No space left", patch=_no_space,
          code=74),
    Fault("eval_read_only_disk", "fitted", None, evaluate(), "Read-only", patch=_read_only, code=74),
    # -- another command writing the same output (issue 32)
    Fault("fit_while_fitting", "fitted", None, fit("--fresh"), **busy("fit")),
    Fault("fit_resume_while_fitting", "fitted", None, resume("--iters", "3"), **busy("fit", "fit --resume")),
    Fault("fit_first_while_fitting", "project", None, fit(), **busy("fit")),
    Fault("render_same_name_while_rendering", "fitted", None, render(), **busy("render/default", "render")),
    Fault("eval_same_name_while_evaluating", "fitted", None, evaluate(), **busy("eval/novel_view_bbox", "eval")),
    Fault("export_same_name_while_exporting", "fitted", None,
          lambda src, out: ["export", str(src), "--device", "cpu", "--format", "glb"],
          **busy("export/default", "export")),
    Fault("ingest_into_a_project_being_ingested", "capture", None, ingest(), **busy(None, "ingest")),
]


@pytest.mark.parametrize("fault", FAULTS, ids=[f.name for f in FAULTS])
def test_fault_is_refused_cleanly(fault: Fault, base, tmp_path, monkeypatch, request):
    if fault.needs:
        pytest.importorskip(fault.needs)
    work = tmp_path / "w"
    src = work / fault.on
    if fault.on == "video":
        src.mkdir(parents=True)
    else:
        shutil.copytree(base[fault.on], src)
    if fault.on not in ("capture", "video"):  # the project records its capture's path: keep one beside it
        shutil.copytree(base["capture"], work / "capture")
    out = work / "out_project"
    if fault.on == "video":
        fault.corrupt(src, request.getfixturevalue("person_frames") if fault.needs else {})
    elif fault.corrupt is not None:
        fault.corrupt(src)
    before = hash_tree(work)
    monkeypatch.delenv("AVATARCTL_DEBUG", raising=False)
    if fault.patch is not None:
        fault.patch(monkeypatch)
    held = hold(fault.busy[0](src, out), fault.busy[1]) if fault.busy else contextlib.nullcontext()
    with held:
        res = CliRunner().invoke(app, fault.args(src, out))
    monkeypatch.undo()
    err = res.stderr.strip()
    assert isinstance(res.exception, SystemExit), f"crashed: {res.exception!r}\n{res.output}"
    assert res.exit_code == fault.code, f"exit {res.exit_code}: {err}"
    assert "Traceback" not in res.output and len(err.splitlines()) == 1, err
    assert err.startswith("error:") and fault.expect in err, err
    assert " -> " in err, f"no fix in the message: {err}"
    assert hash_tree(work) == before, "the command changed the source or left a file behind"
    assert not out.exists()
    if fault.marker:
        assert not (work / "PWNED").exists(), "the pickle payload ran"


def test_the_table_is_big_and_names_are_unique():
    assert len(FAULTS) >= 30 and len({f.name for f in FAULTS}) == len(FAULTS)


# ---- untrusted pickles beyond the capture readers ----------------------------------------------------------------
def test_a_malicious_smpl_model_file_is_refused_before_its_payload_runs(tmp_path):
    from avatarctl.body.registry import load_body_model
    from avatarctl.errors import InputError

    evil = tmp_path / "SMPL_NEUTRAL.pkl"
    evil.write_bytes(pickle.dumps({"v_template": _Payload(tmp_path / "PWNED")}, protocol=2))
    with pytest.raises(InputError, match="posix.system is not allowed") as e:
        load_body_model("smpl", evil)
    assert "\n" not in str(e.value) and not (tmp_path / "PWNED").exists()


def test_safe_npy_reads_plain_object_arrays_and_refuses_code(tmp_path):
    from avatarctl.errors import InputError
    from avatarctl.safe_pickle import load_npy

    good = {"cams": {"K": [np.eye(3)], "T": [np.zeros((3, 1))]}, "ims": [{"ims": ["a/000000.jpg"]}]}
    np.save(tmp_path / "annots.npy", np.array(good, dtype=object), allow_pickle=True)
    back = load_npy(tmp_path / "annots.npy", "annots.npy")
    assert back["ims"] == good["ims"] and np.array_equal(back["cams"]["K"][0], np.eye(3))
    np.save(tmp_path / "plain.npy", np.arange(4.0))
    assert np.array_equal(load_npy(tmp_path / "plain.npy", "plain"), np.arange(4.0))
    np.save(tmp_path / "evil.npy", np.array([1, _Payload(tmp_path / "PWNED")], dtype=object), allow_pickle=True)
    with pytest.raises(InputError, match="not allowed"):
        load_npy(tmp_path / "evil.npy", "fit file")
    assert not (tmp_path / "PWNED").exists()


# ---- what the CLI does with errors that are not bad input -------------------------------------------------------
def _crash(*_a, **_k):
    raise KeyError("boom")


def test_a_bug_is_one_line_with_exit_70_and_a_traceback_only_when_debugging(base, tmp_path, monkeypatch):
    import avatarctl.stages.ingest as stage

    monkeypatch.delenv("AVATARCTL_DEBUG", raising=False)
    monkeypatch.setattr(stage, "run", _crash)
    args = ["ingest", str(base["capture"]), str(tmp_path / "p"), "--no-contact-sheet"]
    res = CliRunner().invoke(app, args)
    err = res.stderr.strip()
    assert res.exit_code == 70 and len(err.splitlines()) == 1 and "Traceback" not in res.output
    assert "internal error: KeyError" in err and "--debug" in err
    for debug_args, env in ((["--debug"], {}), ([], {"AVATARCTL_DEBUG": "1"})):
        res = CliRunner().invoke(app, debug_args + args, env=env)
        assert isinstance(res.exception, KeyError), res.output  # re-raised: Python prints the traceback
        assert "AVATARCTL_DEBUG" not in os.environ  # `--debug` holds for one invocation only
