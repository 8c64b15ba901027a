"""PeopleSnapshot captures (monocular, one rotating subject).

Layout::

    camera.pkl                   latin-1 pickle: camera_f (2), camera_c (2), camera_k (5), camera_rt (3, Rodrigues),
                                 camera_t (3, metres), width, height  (world -> camera)
    masks.hdf5                   'masks' (N, H, W), nonzero = foreground
    reconstructed_poses.hdf5     'betas' (10,), 'pose' (M, 72) SMPL axis-angle, 'trans' (M, 3) metres (M >= N:
                                 the last N rows belong to the N masked frames)
    <name>.mp4 or images/%06d.(jpg|png)   the N video frames

The single camera is named ``cam0``; frame numbers are 0..N-1. camera.pkl is read with
`avatarctl.safe_pickle` (numpy arrays and plain containers only; anything else is refused before it runs).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from avatarctl.body.motion import BodyMotion
from avatarctl.errors import InputError
from avatarctl.io.capture import CaptureSource, FileImages, make_camera, scan_numbered
from avatarctl.geometry.cameras import Camera
from avatarctl.safe_pickle import load_pickle

CAM = "cam0"


def read_peoplesnapshot_camera(path: Path) -> Camera:
    import cv2

    try:
        d = load_pickle(path, "camera.pkl")
        f = np.asarray(d["camera_f"], dtype=np.float64).ravel()
        c = np.asarray(d["camera_c"], dtype=np.float64).ravel()
        k = np.asarray(d.get("camera_k", np.zeros(5)), dtype=np.float64).ravel()
        rt = np.asarray(d["camera_rt"], dtype=np.float64).reshape(3, 1)
        t = np.asarray(d["camera_t"], dtype=np.float64).ravel()
        w, h = int(d["width"]), int(d["height"])
    except InputError:
        raise
    except Exception as e:  # noqa: BLE001 - any unpickling / key problem is the same user error
        raise InputError(f"cannot read camera.pkl ({type(e).__name__}: {e})", where=str(path),
                         fix="expected camera_f, camera_c, camera_k, camera_rt, camera_t, width, height") from None
    if f.size != 2 or c.size != 2 or t.size != 3:
        raise InputError("camera.pkl entries have wrong sizes", where=str(path),
                         fix="camera_f and camera_c need 2 values, camera_t 3")
    K = np.array([[f[0], 0, c[0]], [0, f[1], c[1]], [0, 0, 1.0]])
    return make_camera(path, name=CAM, K=K, R=cv2.Rodrigues(rt)[0], T=t, width=w, height=h, dist=k)


@dataclass
class Hdf5Masks:
    """Masks from ``masks.hdf5['masks']`` [N, H, W] (nonzero = foreground); loaded once, on first use."""

    path: Path
    _masks: np.ndarray | None = field(default=None, repr=False)

    def _load(self) -> np.ndarray:
        if self._masks is None:
            import h5py

            with h5py.File(self.path, "r") as f:
                self._masks = np.asarray(f["masks"]) != 0
        return self._masks

    def read(self, cam: str, frame: int) -> np.ndarray:
        m = self._load()
        if not 0 <= frame < m.shape[0]:
            raise InputError(f"no mask for frame {frame}", where=str(self.path), fix="check --frames")
        return m[frame]

    def where(self, cam: str, frame: int) -> str:
        return f"{self.path}[masks][{frame}]"


@dataclass
class VideoFrames:
    """Frames of a video file, decoded sequentially (ingest asks for frames in ascending order)."""

    path: Path
    _cap: object = field(default=None, repr=False)
    _next: int = 0

    def read(self, cam: str, frame: int) -> np.ndarray:
        import cv2

        if self._cap is None or frame < self._next:
            if self._cap is not None:
                self._cap.release()
            self._cap = cv2.VideoCapture(str(self.path))
            self._next = 0
            if not self._cap.isOpened():
                raise InputError("cannot open video", where=str(self.path), fix="re-encode it (H.264 mp4)")
        img = None
        while self._next <= frame:
            ok, img = self._cap.read()
            if not ok:
                raise InputError(f"video ends before frame {frame}", where=str(self.path),
                                 fix="check that the video has one frame per mask, or select frames with --frames")
            self._next += 1
        return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)

    def where(self, cam: str, frame: int) -> str:
        return f"{self.path} frame {frame}"


def _read_h5(path: Path, keys: tuple[str, ...]) -> dict[str, np.ndarray]:
    import h5py

    if not path.is_file():
        raise InputError(f"{path.name} missing", where=str(path.parent), fix="PeopleSnapshot captures need it")
    try:
        with h5py.File(path, "r") as f:
            out = {}
            for k in keys:
                if k not in f:
                    raise InputError(f"{path.name} has no {k!r} dataset", where=str(path),
                                     fix=f"expected datasets {', '.join(keys)}")
                out[k] = np.asarray(f[k])
            return out
    except OSError as e:
        raise InputError(f"cannot read {path.name} ({e})", where=str(path), fix="re-download it") from None


def read_peoplesnapshot(root: Path) -> CaptureSource:
    root = Path(root)
    camera = read_peoplesnapshot_camera(root / "camera.pkl")
    import h5py

    mpath = root / "masks.hdf5"
    try:
        with h5py.File(mpath, "r") as f:
            if "masks" not in f:
                raise InputError("masks.hdf5 has no 'masks' dataset", where=str(mpath), fix="re-download it")
            n_masks, mh, mw = f["masks"].shape
    except (OSError, ValueError) as e:
        raise InputError(f"cannot read masks.hdf5 ({e})", where=str(mpath), fix="re-download it") from None
    if (mw, mh) != (camera.width, camera.height):
        raise InputError(f"masks are {mw}x{mh} but camera.pkl says {camera.width}x{camera.height}", where=str(mpath),
                         fix="use the masks that belong to this video")

    poses = _read_h5(root / "reconstructed_poses.hdf5", ("betas", "pose", "trans"))
    pose, trans = poses["pose"].astype(np.float64), poses["trans"].astype(np.float64)
    where = str(root / "reconstructed_poses.hdf5")
    if pose.ndim != 2 or pose.shape[1] != 72 or trans.shape != (pose.shape[0], 3):
        raise InputError(f"poses {pose.shape} / trans {trans.shape}: expected (M, 72) / (M, 3)", where=where,
                         fix="write SMPL axis-angle poses (72 per frame) and translations (3 per frame)")
    if pose.shape[0] < n_masks:
        raise InputError(f"frame-count mismatch: {pose.shape[0]} poses for {n_masks} masks", where=where,
                         fix="use the pose file that belongs to these masks")
    pose, trans = pose[-n_masks:], trans[-n_masks:]  # the last N poses belong to the N masked frames
    if not (np.isfinite(pose).all() and np.isfinite(trans).all()):
        raise InputError("poses contain NaN or inf", where=where, fix="re-run the pose reconstruction")
    betas = np.asarray(poses["betas"], dtype=np.float64).reshape(-1, np.shape(poses["betas"])[-1])[0]
    motion = BodyMotion(body_model="smpl", frame_index=np.arange(n_masks), global_orient=pose[:, :3],
                        body_pose=pose[:, 3:], transl=trans, betas=betas)

    frames_dir = scan_numbered(root / "images")
    videos = sorted(root.glob("*.mp4"))
    if frames_dir:
        images = FileImages({(CAM, f): p for f, p in frames_dir.items()})
        have = set(frames_dir)
        note = "frames from images/"
    elif videos:
        images = VideoFrames(videos[0])
        import cv2

        cap = cv2.VideoCapture(str(videos[0]))
        n_video = int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) if cap.isOpened() else 0
        cap.release()
        have = set(range(min(n_video, n_masks))) if n_video else set(range(n_masks))
        note = f"frames from {videos[0].name}"
    else:
        raise InputError("no frames (images/ folder or .mp4 video)", where=str(root),
                         fix="put the video (<name>.mp4) or its frames images/%06d.jpg in the capture folder")
    return CaptureSource(format="peoplesnapshot", root=root, cameras=[camera], image_frames={CAM: have},
                         images=images, fits=motion, fits_where=where, masks=Hdf5Masks(mpath),
                         mask_frames={CAM: set(range(n_masks))},
                         notes=[note, f"last {n_masks} of the reconstructed poses used (one per mask)"])
