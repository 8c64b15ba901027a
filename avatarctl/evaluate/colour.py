"""The per-camera colour transform (issue 51: cameras that disagree in exposure and white balance), stated once.

A camera c records the subject's colour x as gain_c * x + offset_c, per channel (3 gains + 3 offsets: exposure and
white balance act per channel of the sensor, a diagonal von Kries transform; a full 3x3 would also let the transform
trade colour with the avatar's albedo between cameras, which 3 or 4 training cameras do not pin down). The transform
acts on the foreground only: a pixel rendered over the training background bg with opacity alpha holds the
premultiplied colour f = rgb - (1 - alpha) bg, and camera c sees

    gain_c * f + alpha * offset_c + (1 - alpha) * bg                                   (`apply_colour`)

so the background (a fixed colour, not a photograph: the target is rgb * mask + bg * (1 - mask)) never changes.
Used by the fit (`model/colour.py`: learned per training camera, torch tensors), by `ingest` (`SharedColours`: every
camera's gains from the posed body's colours across cameras, `CameraGains`, saved as ingest/camera_colour.json) and
by `eval` (a held-out camera rendered through those gains; `estimate_colour`: a held-out camera's transform from half
of each image, NeRF-W's protocol; numpy). The arithmetic works on numpy arrays and torch tensors alike.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from avatarctl.geometry.cameras import Camera


def apply_colour(rgb: Any, alpha: Any, background: Any, gain: Any, offset: Any) -> Any:
    """rgb [..., 3] composited over `background` [3] with opacity alpha [...] -> the same pixels with the
    foreground's colour transformed by gain, offset ([3], or [..., 3] per pixel); see the module docstring."""
    bg = (1 - alpha)[..., None] * background  # [..., 3]
    return gain * (rgb - bg) + alpha[..., None] * offset + bg


def estimate_colour(rgb: np.ndarray, alpha: np.ndarray, gt: np.ndarray, background: np.ndarray, mask: np.ndarray,
                    ridge: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
    """The transform (gain [3], offset [3] = 0) of a camera's exposure and white balance, from the `mask` pixels:
    per channel the ratio of the summed foreground colours where the render is opaque (alpha >= 0.5), gain_k =
    (sum t_k + r) / (sum f_k + r) with r = `ridge` times the pixel count (identity without such pixels). rgb, gt [H, W, 3], alpha [H, W], mask [H, W]
    bool; float64 sums. Why a ratio and no offset: a held-out render is blurrier than its photograph and a little
    misaligned, and a least-squares fit of gain and offset regresses towards the mean colour (on 300 s fits of synth
    realistic and its clean twin, `python -m benchmarks.realistic_capture OUT --only clean,realistic --colour`, it
    found gains of 0.67-0.80 for a camera 1.19x brighter, and scored the realistic capture's right halves 0.8 dB
    below the plain render); exposure and white balance are gains (the module docstring)."""
    m = np.asarray(mask, bool) & (np.asarray(alpha) >= 0.5)  # where the render holds the subject
    a = alpha[m].astype(np.float64)  # [n]
    bg = np.asarray(background, np.float64).reshape(3)
    f = rgb[m].astype(np.float64) - (1 - a)[:, None] * bg  # [n, 3] premultiplied foreground
    t = gt[m].astype(np.float64) - (1 - a)[:, None] * bg  # what the transformed foreground must match
    lam = ridge * max(int(m.sum()), 1)
    return (t.sum(0) + lam) / (f.sum(0) + lam), np.zeros(3)


def halves(mask: np.ndarray, crop: tuple[int, int, int, int]) -> tuple[np.ndarray, np.ndarray]:
    """(left, right) halves of the evaluation `mask` [H, W], split at the middle column of its bounding rectangle
    `crop` (x0, y0, x1, y1): NeRF-W's held-out protocol fits the appearance on the left half, scores the right."""
    x0, _, x1, _ = crop
    cols = np.arange(mask.shape[1])[None, :]
    mid = (x0 + x1) // 2
    return mask & (cols < mid), mask & (cols >= mid)


CROSS_CAMERA = ("the median over posed-body points seen by both cameras (front-facing, cos >= 0.3, inside both masks, "
                "channels in (0.02, 0.98)) of the log colour ratio of each pair, blurred images; log-gains by "
                "weighted least squares, the training cameras' mean = 1")


@dataclass(frozen=True)
class CameraGains:
    """Each camera's exposure and white balance as per-channel gains on the subject's colour, relative to the
    training cameras' mean (the colour an avatar fitted without per-camera transforms learns; the gauge of
    `model/colour.py`), estimated at ingest by `SharedColours` (`CROSS_CAMERA`). ingest/camera_colour.json."""

    views: tuple[str, ...]  # every camera of the capture
    gain: np.ndarray  # [C, 3]; 1 for a camera that shares no points with a training camera
    points: np.ndarray  # [C] int: body points the camera shared with the others (summed over pairs and frames)
    estimated: np.ndarray  # [C] bool: linked to a training camera through shared points
    frames: int  # frames the estimate used
    method: str = CROSS_CAMERA

    def __post_init__(self) -> None:
        C = len(self.views)
        assert self.gain.shape == (C, 3) and self.points.shape == (C,) and self.estimated.shape == (C,), \
            f"gain {self.gain.shape}, points {self.points.shape}, estimated {self.estimated.shape} for {C} views"

    def of(self, view: str) -> np.ndarray | None:
        """[3] the gains of camera `view`, None when it has no estimate."""
        if view not in self.views or not self.estimated[self.views.index(view)]:
            return None
        return self.gain[self.views.index(view)]

    def to_json(self) -> dict[str, Any]:
        return {"method": self.method, "frames": self.frames, "reference": "the training cameras' mean",
                "cameras": {v: {"gain": [round(float(g), 5) for g in self.gain[i]], "points": int(self.points[i]),
                                "estimated": bool(self.estimated[i])} for i, v in enumerate(self.views)}}

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> "CameraGains":
        cams = d["cameras"]
        views = tuple(str(v) for v in cams)
        return cls(views=views, gain=np.array([[float(g) for g in cams[v]["gain"]] for v in views]).reshape(-1, 3),
                   points=np.array([int(cams[v]["points"]) for v in views], dtype=np.int64),
                   estimated=np.array([bool(cams[v]["estimated"]) for v in views], dtype=bool),
                   frames=int(d["frames"]), method=str(d["method"]))


class SharedColours:
    """The posed body's colours as every pair of cameras sees them, frame by frame (`add`), and the cameras' gains
    that explain them (`solve`): a surface point has one colour, so where two cameras see the same point, the ratio
    of their pixels is the ratio of their gains (`CROSS_CAMERA`). Without per-camera gains the avatar learns the
    training cameras' mean colour, and a held-out camera shows it through its own gain: this estimate, from its
    images of the training frames and the body fits alone (no render), is how `eval` shows it."""

    MIN_COS = 0.3  # both cameras see the point from within ~72 degrees of its normal (grazing views misalign)
    POINTS = 2000  # body vertices read per frame (a fixed random subset: the medians need thousands, not all)
    DARK, BRIGHT = 0.02, 0.98  # clipped channels carry no ratio

    def __init__(self, views: list[str] | tuple[str, ...]):
        self.views = tuple(views)
        self.ratios: dict[tuple[int, int], list[np.ndarray]] = {}  # (a, b), a < b -> [n, 3] log(col_a / col_b)
        self.frames = 0

    def add(self, cameras: list[Camera], images: list[np.ndarray], masks: list[np.ndarray], vertices: np.ndarray,
            faces: np.ndarray) -> None:
        """One frame: `cameras`, RGB uint8 `images` [H, W, 3] and bool `masks` [H, W] in `views` order, the posed
        body `vertices` [V, 3] (metres) and `faces` [T, 3]."""
        import cv2

        from avatarctl.geometry.normals import vertex_normals
        from avatarctl.geometry.raycast import RayCaster, seen_by
        from avatarctl.geometry.triangulate import project, projection_matrices

        every = np.asarray(vertices, np.float64)
        pick = np.sort(np.random.default_rng(self.frames).permutation(len(every))[:self.POINTS])
        X = every[pick]
        seen = seen_by(RayCaster(every, faces), np.stack([c.center for c in cameras]), X,
                       vertex_normals(every, faces)[pick], self.MIN_COS)  # [C, n]
        px, depth = project(projection_matrices(cameras), X)  # [n, C, 2]
        cols = np.zeros((len(cameras), len(X), 3))
        for c, (img, m) in enumerate(zip(images, masks)):
            sigma = max(1.0, 0.01 * min(img.shape[:2]))  # blur: the fits are off by a pixel or two
            im = cv2.GaussianBlur(img.astype(np.float32) / 255.0, (0, 0), sigma)
            u, v = np.round(px[:, c, 0]).astype(np.int64), np.round(px[:, c, 1]).astype(np.int64)
            ok = seen[c] & (depth[:, c] > 0) & (u >= 0) & (v >= 0) & (u < m.shape[1]) & (v < m.shape[0])
            ok[ok] &= np.asarray(m, bool)[v[ok], u[ok]]
            cols[c, ok] = im[v[ok], u[ok]]
            seen[c] = ok & ((cols[c] > self.DARK) & (cols[c] < self.BRIGHT)).all(-1)
        for a in range(len(cameras)):
            for b in range(a + 1, len(cameras)):
                both = seen[a] & seen[b]
                if both.any():
                    self.ratios.setdefault((a, b), []).append(np.log(cols[a, both]) - np.log(cols[b, both]))
        self.frames += 1

    def solve(self, train_views: list[str] | tuple[str, ...], min_points: int = 50) -> CameraGains:
        """The gains (`CameraGains`): per pair with >= `min_points` shared points, its median log ratio per channel;
        log-gains by least squares weighted by sqrt(points), with the training cameras' mean log-gain 0 in each
        group of linked cameras; a camera linked to no training camera keeps gain 1 (`estimated` False)."""
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import connected_components

        C = len(self.views)
        pairs = {k: np.concatenate(v) for k, v in self.ratios.items() if sum(len(x) for x in v) >= min_points}
        points = np.zeros(C, dtype=np.int64)
        for (a, b), r in pairs.items():
            points[a] += len(r)
            points[b] += len(r)
        train = np.array([v in set(train_views) for v in self.views])
        gain, estimated = np.ones((C, 3)), np.zeros(C, dtype=bool)
        if pairs:
            e = np.array(list(pairs))
            _, group = connected_components(coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(C, C)),
                                            directed=False)
            for g in np.unique(group):
                members = np.where(group == g)[0]
                if len(members) < 2 or not train[members].any():
                    continue
                rows, rhs = [], []
                for (a, b), r in pairs.items():
                    if group[a] == g:
                        row = np.zeros(C)
                        row[a], row[b] = 1.0, -1.0
                        w = np.sqrt(len(r))
                        rows.append(w * row)
                        rhs.append(w * np.median(r, 0))
                gauge = np.zeros(C)
                gauge[members[train[members]]] = 1.0 / train[members].sum()
                rows.append(1e3 * gauge)  # the training cameras' mean log-gain is 0
                rhs.append(np.zeros(3))
                A = np.stack(rows)[:, members]
                log_gain = np.linalg.lstsq(A, np.stack(rhs), rcond=None)[0]  # [members, 3]
                gain[members] = np.exp(log_gain)
                estimated[members] = True
        return CameraGains(views=self.views, gain=gain, points=points, estimated=estimated, frames=self.frames)
