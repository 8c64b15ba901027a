"""Foreground masks from background plates: colour difference + morphology + body-seeded refinement.

All inputs are in the same (undistorted) image geometry. Steps:

1. difference: Euclidean RGB distance between frame and plate, grayscale-closed with a 3x3 disk (a textured
   garment has isolated pixels that happen to match the plate; closing fills such pits but keeps edges);
   ``> threshold`` is foreground;
2. body seed: the projected posed body mesh shrunk by 2 px is foreground whatever its colour;
3. GrabCut (``cv2.grabCut``, colour GMMs + graph cut) deciding only the uncertain boundary band: the outer
   1-px ring of the thresholded region (probable foreground) and a 2-px ring outside it that differs by more
   than half the threshold (probable background); everything deeper inside is definite foreground, everything
   else definite background. (Letting GrabCut decide whole regions lost textured garment parts that happen to
   match the plate's colours.) Parameters were chosen on `avatarctl synth` small-preset frames (docs/formats.md);
4. clean-up: keep the connected components that touch the body silhouette (drops shadows and plate changes
   away from the subject), fill enclosed holes smaller than 1 % of the foreground;
5. the outline's pixels decided by their share of the person's local contrast with the plate (`sharpen_outline`).

Without a plate, a static camera's plate is estimated from its own frames (`estimate_plate`: per pixel, the median
of the frames in which a detector's person mask, grown by a margin, leaves it uncovered) and a detector's mask is
refined against it (`refine_mask`: in a ring about the detector's outline, pixels that clearly match the plate are
dropped and pixels that clearly differ from it added; then `sharpen_outline` decides the outline's pixels by the
share of the person's local contrast with the plate they carry).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class MattingParams:
    threshold: float = 20.0  # RGB distance (0..441) above which a pixel differs from the plate
    diff_close_px: int = 1  # grayscale closing of the difference: fills 1-px texture pits, keeps edges
    open_px: int = 0  # opening radius of the thresholded difference (speckle removal; 0: off)
    erode_silhouette_px: int = 2  # the projected body shrunk by this much is definite foreground
    grabcut_iters: int = 3  # GrabCut iterations on the uncertain boundary band (0: off)
    band_px: int = 2  # width of that band outside the thresholded region
    max_hole_fraction: float = 0.01  # enclosed holes smaller than this fraction of the foreground are filled
    half_max_px: int = 0  # boundary band (px) where a pixel must reach half the local contrast (0: off)

    def __post_init__(self) -> None:
        if self.threshold <= 0 or self.grabcut_iters < 0 or min(self.diff_close_px, self.open_px,
                                                                  self.erode_silhouette_px, self.band_px) < 0:
            raise ValueError(f"bad matting parameters {self}")


def _disk(r: int) -> np.ndarray:
    import cv2

    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))


def color_difference(rgb: np.ndarray, background: np.ndarray) -> np.ndarray:
    """[H, W] float32 Euclidean RGB distance of two uint8 [H, W, 3] images (no blur: blurring widens the
    silhouette)."""
    return np.sqrt(((rgb.astype(np.float32) - background.astype(np.float32)) ** 2).sum(axis=-1))


def half_max_edges(fg: np.ndarray, diff: np.ndarray, band_px: int) -> np.ndarray:
    """Sharpen the boundary of `fg` (uint8 [H, W]): a pixel within `band_px` of the edge stays foreground only if
    its difference reaches half the largest difference nearby (a mixed pixel is > 50 % subject). Resampling,
    anti-aliasing and JPEG chroma subsampling spread an edge over 1-2 px; a fixed threshold keeps all of them."""
    import cv2

    k = 2 * band_px + 1
    local_max = cv2.dilate(diff * (fg > 0), np.ones((k, k), np.uint8))
    edge = (fg > 0) & (cv2.erode(fg, _disk(band_px)) == 0)
    return (fg.astype(bool) & (~edge | (diff >= 0.5 * local_max))).astype(np.uint8)


def background_mask(rgb: np.ndarray, background: np.ndarray, silhouette: np.ndarray,
                    params: MattingParams = MattingParams()) -> np.ndarray:
    """Foreground mask, bool [H, W], of frame `rgb` [H, W, 3] against plate `background` [H, W, 3], seeded by the
    projected body mesh `silhouette` (bool [H, W])."""
    import cv2

    if rgb.shape != background.shape:
        raise ValueError(f"frame {rgb.shape} and background {background.shape} differ in size")
    raw = diff = color_difference(rgb, background)
    if params.diff_close_px:
        diff = cv2.morphologyEx(diff, cv2.MORPH_CLOSE, _disk(params.diff_close_px))
    fg = (diff > params.threshold).astype(np.uint8)
    if params.open_px:
        fg = cv2.morphologyEx(fg, cv2.MORPH_OPEN, _disk(params.open_px))
    if params.half_max_px:
        fg = half_max_edges(fg, diff, params.half_max_px)
    sil = silhouette.astype(np.uint8)
    if params.erode_silhouette_px:  # a body is not see-through, whatever its colour
        fg |= cv2.erode(sil, _disk(params.erode_silhouette_px))
    out = fg > 0
    if params.grabcut_iters and out.any():
        out = _grabcut_band(rgb, diff, fg, params)
    return sharpen_outline(raw, np.ones(out.shape, bool), _clean(out, sil > 0, params))


def _grabcut_band(rgb: np.ndarray, diff: np.ndarray, fg: np.ndarray, params: MattingParams) -> np.ndarray:
    """GrabCut deciding only the uncertain band: the outer ring of `fg` (probable foreground) and a ring of
    `band_px` outside it where the difference exceeds half the threshold (probable background)."""
    import cv2

    inside = fg > 0
    gc = np.full(diff.shape, cv2.GC_BGD, dtype=np.uint8)
    ring_out = (cv2.dilate(fg, _disk(params.band_px)) > 0) & ~inside
    gc[ring_out & (diff > 0.5 * params.threshold)] = cv2.GC_PR_BGD
    gc[inside] = cv2.GC_PR_FGD
    gc[cv2.erode(fg, _disk(1)) > 0] = cv2.GC_FGD
    if not (gc == cv2.GC_FGD).any():
        return inside
    ys, xs = np.nonzero(cv2.dilate(fg, _disk(params.band_px + 8)))
    y0, y1, x0, x1 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
    sub = np.ascontiguousarray(gc[y0:y1, x0:x1])
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    cv2.setRNGSeed(0)
    cv2.grabCut(np.ascontiguousarray(rgb[y0:y1, x0:x1, ::-1]), sub, None, bgd, fgd, params.grabcut_iters,
                cv2.GC_INIT_WITH_MASK)
    out = np.zeros(diff.shape, dtype=bool)
    out[y0:y1, x0:x1] = (sub == cv2.GC_FGD) | (sub == cv2.GC_PR_FGD)
    return out


def _clean(mask: np.ndarray, silhouette: np.ndarray, params: MattingParams) -> np.ndarray:
    """Keep the components touching the silhouette (all, if none does); fill small enclosed holes."""
    import cv2

    fg = mask.astype(bool)
    m = _connected_to(fg, silhouette.astype(bool) & fg).astype(np.uint8)
    area = int(m.sum())
    n, labels, stats, _ = cv2.connectedComponentsWithStats((1 - m).astype(np.uint8), connectivity=4)
    H, W = m.shape
    for i in range(1, n):
        x, y, w, h, a = stats[i]
        touches_border = x == 0 or y == 0 or x + w == W or y + h == H
        if not touches_border and a < params.max_hole_fraction * max(area, 1):
            m[labels == i] = 1
    return m > 0


PLATE_FRAMES = 32  # frames of a camera (evenly spaced) that its estimated plate is the median of
PLATE_MIN_SHARE = 0.15  # a pixel's plate is known where at least this share of those frames (and 3) show background
REFINE_MATCH = 12.0  # refine_mask: RGB distance (0..441) below which a pixel is the plate's (noise, JPEG: ~5-10)
REFINE_DIFFER = 45.0  # ... and above which it is not
EDGE_WINDOW = 9  # sharpen_outline: the window (px) over which the person's contrast with the plate is averaged
EDGE_FRACTION = 0.4  # ... and the share of it an outline pixel's contrast must reach to be the person's


def estimate_plate(images: np.ndarray, masks: np.ndarray, margin_px: int) -> tuple[np.ndarray, np.ndarray]:
    """A static camera's background plate from its frames `images` uint8 [K, H, W, 3] and their person `masks` bool
    [K, H, W]: per pixel, the median colour over the frames whose mask, grown by `margin_px`, leaves it uncovered.
    -> (plate uint8 [H, W, 3], known bool [H, W]: uncovered in at least `PLATE_MIN_SHARE` of the frames and 3; the
    plate is 0 elsewhere: a pixel the person always covers has no plate)."""
    import warnings

    import cv2

    K, H, W = masks.shape
    if images.shape != (K, H, W, 3):
        raise ValueError(f"images {images.shape} and masks {masks.shape} differ")
    grow = _disk(margin_px)
    background = np.stack([cv2.dilate(m.astype(np.uint8), grow) == 0 for m in masks])  # [K, H, W]
    known = background.sum(0) >= max(3, int(np.ceil(PLATE_MIN_SHARE * K)))
    plate = np.zeros((H, W, 3), dtype=np.uint8)
    for r in range(0, H, 64):  # in strips: K float copies of a whole image would be K x 12 bytes a pixel
        rows = slice(r, r + 64)
        seen = np.where(background[:, rows, :, None], images[:, rows].astype(np.float32), np.nan)
        with warnings.catch_warnings():  # "All-NaN slice": a pixel no frame shows uncovered (expected)
            warnings.simplefilter("ignore", RuntimeWarning)
            med = np.nanmedian(seen, axis=0)
        plate[rows] = np.where(known[rows, :, None], np.rint(np.nan_to_num(med)), 0).astype(np.uint8)
    return plate, known


def plate_agrees(plate: np.ndarray, estimate: np.ndarray, known: np.ndarray) -> bool:
    """Whether a capture's background `plate` (uint8 [H, W, 3]) shows what the camera's frames show: its median RGB
    distance to the `estimate` from the frames (`estimate_plate`, `known` bool [H, W]) over the known pixels is below
    `REFINE_MATCH` (the distance at which `refine_mask` still takes a pixel for the plate's). A plate shot at another
    exposure, white balance or framing than the frames fails; where the frames show no background pixel there is
    nothing to check and the plate is taken as it is."""
    if plate.shape != estimate.shape:
        return False
    return not known.any() or float(np.median(color_difference(plate, estimate)[known])) < REFINE_MATCH


def refine_mask(rgb: np.ndarray, plate: np.ndarray, known: np.ndarray, mask: np.ndarray, band_px: int,
                match: float = REFINE_MATCH, differ: float = REFINE_DIFFER) -> np.ndarray:
    """A detector's person `mask` (bool [H, W]) of frame `rgb` [H, W, 3] refined against an estimated `plate`
    (`estimate_plate`) in the ring of `band_px` about its outline, where the plate is `known`: a mask pixel whose
    colour matches the plate (RGB distance < `match`) is dropped, a pixel outside that differs from it (> `differ`)
    is added; between the two, and everywhere else, the detector decides. Of what is added, only the parts connected to
    the mask shrunk by `band_px` are kept. Then the outline is placed by `sharpen_outline`. -> bool [H, W]."""
    import cv2

    m = mask.astype(np.uint8)
    core = cv2.erode(m, _disk(band_px)) > 0
    ring = (cv2.dilate(m, _disk(band_px)) > 0) & ~core & known
    diff = color_difference(rgb, plate)
    out = mask.astype(bool).copy()
    out[ring & out & (diff < match)] = False
    out[ring & ~mask.astype(bool) & (diff > differ)] = True
    return sharpen_outline(diff, known, _connected_to(out, core))


def _connected_to(mask: np.ndarray, core: np.ndarray) -> np.ndarray:
    """The parts of bool `mask` connected (8-neighbours) to `core`, and `core` itself; `mask` when none are."""
    import cv2

    n, labels = cv2.connectedComponents(mask.astype(np.uint8), connectivity=8)
    keep = np.unique(labels[core & mask])
    keep = keep[keep > 0]
    return (np.isin(labels, keep) | core) if keep.size else mask


def sharpen_outline(diff: np.ndarray, known: np.ndarray, mask: np.ndarray, window: int = EDGE_WINDOW,
                    fraction: float = EDGE_FRACTION) -> np.ndarray:
    """The outline of a person `mask` (bool [H, W]) placed by the person's own contrast with the plate: a pixel within
    1 px of the outline (either side) where the plate is `known` is the person's when its difference to the plate
    `diff` ([H, W], RGB distance) reaches `fraction` of the mean difference of the mask's core (shrunk by 2 px) within
    the `window` about it. A fixed threshold (`refine_mask`'s) keeps a half-covered pixel only where the person
    contrasts strongly with the background; this rule keeps it wherever the pixel carries a good share of the local
    contrast (`half_max_edges` does the same against a given plate with the largest difference nearby, which a print
    inflates). Pixels with no core in their window keep the mask's value. -> bool [H, W].

    `window` and `fraction` were chosen on synth `realistic` seeds 0 / 1 / 7 and `phone` seed 0 and checked on
    `realistic` seed 3 and `phone` seed 1: mask IoU +0.001 to +0.005 on all six (`benchmarks.mask_accuracy`;
    `docs/experiments/sharp_outline_2026-12-03/`)."""
    import cv2

    m = mask.astype(np.uint8)
    core = cv2.erode(m, _disk(2)) > 0
    k = (window, window)
    weight = cv2.boxFilter(core.astype(np.float32), -1, k, normalize=False)
    contrast = cv2.boxFilter(diff * core, -1, k, normalize=False) / np.maximum(weight, 1e-6)
    ring = (cv2.dilate(m, _disk(1)) > 0) & (cv2.erode(m, _disk(1)) == 0) & known & (weight > 0)
    out = mask.astype(bool).copy()
    out[ring] = diff[ring] >= fraction * contrast[ring]
    return _connected_to(out, core)


def iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two bool masks (1.0 when both are empty)."""
    union = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / union) if union else 1.0
