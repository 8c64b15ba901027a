"""EasyMocap camera calibration: `intri.yml` / `extri.yml` (OpenCV FileStorage, `%YAML:1.0`).

intri.yml: `names` (sequence of camera names), `K_<cam>` 3x3, `dist_<cam>` 1x5 (k1 k2 p1 p2 k3; 1x4 accepted),
optional `H_<cam>`, `W_<cam>` (image size). extri.yml: `names`, `R_<cam>` 3x1 Rodrigues, `Rot_<cam>` 3x3,
`T_<cam>` 3x1 metres, with x_cam = Rot @ x_world + T.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from avatarctl.atomic import atomic_path
from avatarctl.errors import InputError
from avatarctl.geometry.cameras import Camera
from avatarctl.io.capture import make_camera


_FIX_YAML = "re-export it with cv2.FileStorage (EasyMocap format, starting with %YAML:1.0); a cut-off copy needs a " \
            "fresh copy"


def _cv_reason(e: Exception) -> str:
    """The first line OpenCV gives for a parse error, without its source-file prefix."""
    cause = e.__cause__ or e.__context__ or e
    text = " ".join(str(cause).split())
    return text.split("error: ")[-1][:160] or type(e).__name__


def _open_storage(path: Path):
    """`cv2.FileStorage` opened for reading, or a one-line `InputError` naming the file (empty, cut off, not UTF-8,
    not YAML). OpenCV parses the whole file on open and raises `cv2.error` (wrapped in a SystemError by the Python
    binding) on a syntax error."""
    import cv2

    if path.stat().st_size == 0:
        raise InputError(f"calibration file {path.name} is empty", where=str(path), fix=_FIX_YAML)
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as e:
        raise InputError(f"cannot parse calibration file {path.name} ({_cv_reason(e)})", where=str(path),
                         fix=_FIX_YAML) from None
    if not fs.isOpened() or not fs.root().isMap():
        raise InputError(f"cannot parse calibration file {path.name} (not OpenCV FileStorage YAML)", where=str(path),
                         fix=_FIX_YAML)
    return fs


def _read_names(fs, path: Path) -> list[str]:
    node = fs.getNode("names")
    if node.empty():
        raise InputError("calibration file has no 'names' list", where=str(path),
                         fix="add a `names` sequence with one entry per camera (EasyMocap format)")
    return [node.at(i).string() for i in range(node.size())]


def _mat(fs, key: str, path: Path, required: bool = True) -> np.ndarray | None:
    node = fs.getNode(key)
    if node.empty():
        if required:
            raise InputError(f"calibration entry {key} is missing", where=str(path),
                             fix=f"add {key} for every camera listed in `names`")
        return None
    if node.isInt() or node.isReal():
        return np.array([[node.real()]])
    m = node.mat() if node.isMap() else None  # a cut-off file leaves an empty `!!opencv-matrix` (not a map)
    if m is None:
        raise InputError(f"calibration entry {key} is not a matrix (is the file cut off?)", where=str(path),
                         fix="write it as an opencv-matrix; " + _FIX_YAML)
    return np.asarray(m, dtype=np.float64)


def read_easymocap_cameras(capture_dir: Path, image_size: dict[str, tuple[int, int]] | None = None) -> list[Camera]:
    """Read `capture_dir/intri.yml` + `extri.yml` into `Camera`s (in the order of intri's `names`).

    `image_size` maps camera name -> (width, height) for files without `H_<cam>`/`W_<cam>`.
    """
    import cv2

    capture_dir = Path(capture_dir)
    ipath, epath = capture_dir / "intri.yml", capture_dir / "extri.yml"
    for p in (ipath, epath):
        if not p.is_file():
            raise InputError(f"missing calibration file {p.name}", where=str(capture_dir),
                             fix="EasyMocap captures need intri.yml and extri.yml beside images/")
    fi = _open_storage(ipath)
    try:
        fe = _open_storage(epath)
    except InputError:
        fi.release()
        raise
    try:
        names = _read_names(fi, ipath)
        enames = set(_read_names(fe, epath))
        missing = [n for n in names if n not in enames]
        if missing:
            raise InputError(f"cameras {missing} are in intri.yml but not in extri.yml", where=str(epath),
                             fix="calibrate or remove those cameras so both files list the same names")
        cams = []
        for n in names:
            K = _mat(fi, f"K_{n}", ipath)
            dist = _mat(fi, f"dist_{n}", ipath, required=False)
            H = _mat(fi, f"H_{n}", ipath, required=False)
            W = _mat(fi, f"W_{n}", ipath, required=False)
            Rot = _mat(fe, f"Rot_{n}", epath, required=False)
            if Rot is None:
                Rot = cv2.Rodrigues(_mat(fe, f"R_{n}", epath).reshape(3, 1))[0]
            T = _mat(fe, f"T_{n}", epath)
            if H is not None and W is not None:
                w, h = int(W.ravel()[0]), int(H.ravel()[0])
            elif image_size and n in image_size:
                w, h = image_size[n]
            else:
                raise InputError(f"image size of camera {n} unknown", where=str(ipath),
                                 fix=f"add H_{n} and W_{n} to intri.yml")
            if K.shape != (3, 3) or Rot.shape != (3, 3) or T.size != 3:
                raise InputError(f"camera {n} has malformed K/R/T shapes {K.shape}/{Rot.shape}/{T.shape}",
                                 where=str(capture_dir), fix="K must be 3x3, Rot 3x3 (or R 3x1 Rodrigues), T 3x1")
            cams.append(make_camera(f"{ipath} + {epath.name}", name=n, K=K, R=Rot, T=T.ravel(), width=w, height=h,
                                    dist=np.zeros(5) if dist is None else dist.ravel()))
        return cams
    finally:
        fi.release()
        fe.release()


def write_easymocap_cameras(out_dir: Path, cameras: list[Camera]) -> None:
    """Write `out_dir/intri.yml` and `out_dir/extri.yml` (atomically) in the EasyMocap convention."""
    import cv2

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    for fname, intri in (("intri.yml", True), ("extri.yml", False)):
        with atomic_path(out_dir / fname) as tmp:
            fs = cv2.FileStorage(str(tmp), cv2.FILE_STORAGE_WRITE)
            fs.startWriteStruct("names", cv2.FileNode_SEQ)
            for c in cameras:
                fs.write("", c.name)
            fs.endWriteStruct()
            for c in cameras:
                if intri:
                    fs.write(f"K_{c.name}", c.K)
                    fs.write(f"dist_{c.name}", c.dist.reshape(1, 5))
                    fs.write(f"H_{c.name}", int(c.height))
                    fs.write(f"W_{c.name}", int(c.width))
                else:
                    fs.write(f"R_{c.name}", cv2.Rodrigues(c.R)[0])
                    fs.write(f"Rot_{c.name}", c.R)
                    fs.write(f"T_{c.name}", c.T.reshape(3, 1))
            fs.release()
