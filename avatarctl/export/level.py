"""The surface level chosen by the training images (`avatarctl export --threshold auto`, issue 33).

The body level (`mesh.body_level`: the 25 % quantile of the density 1 cm inside the posed body model's skin, at most
10 / metre) is a guess from the field alone, and the best level is not a fixed multiple of it: on a full tiny demo
(2,000 steps) the body level is 7.79 / m and 4 / m scores 0.64 dB better on the held-out views; on synth tight (MLP,
4,185 steps) it is 10 / m (the cap) and 20 / m scores 0.84 dB better (docs/export_view.md). So the level is chosen
per mesh by what it shows: candidate meshes are rendered in a few of the project's TRAINING views (the images the fit
saw; the held-out views stay for `--score`) and the one closest to the photographs wins.

Steps (`choose_level`):
1. the candidates: levels b * LEVEL_STEP^k, b the body level, k an integer in [-LEVEL_STEPS, LEVEL_STEPS]
   (b / 4 .. 4 b); the grid must be refined around b (`mesh.density_grid(level=b)`), which makes it exact at the
   crossings of every level in [b / 4, 4 b], so every candidate is marched on that one grid;
2. the search: k = 0 and both neighbours are scored; then, from the better neighbour, one step at a time in its
   direction while the score strictly improves (the training-view PSNR rises to one peak and falls on both projects
   measured); k = 0 is kept unless a neighbour beats it;
3. a candidate's score: marching cubes at its level (`mesh.marching_cubes`), one ray per pixel of each scoring image
   cast against it (`raster.cast_pixels`), the vertices of the faces hit coloured (the `mesh.VertexColourFn` the
   exported mesh gets: only those vertices show in the images; the head-on bake computes only them), the images
   shaded (`raster.shade`) and scored with
   the PSNR over the eval bbox region (`evaluate.metrics.psnr`), averaged over the images; a level with no surface
   loses to every level with one;
4. the mesh at the chosen level is that candidate with the rest of its vertices coloured: the same mesh (vertices,
   faces, colours) `mesh.extract_mesh` gives at that level.

Scoring images are at most SCORE_MAX_SIDE pixels on their long side (`scoring_image` scales larger cameras down and
area-averages the photograph), so the cost of a candidate (its baked vertices: about 3 per pixel hit) is bounded
whatever the capture's resolution.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from avatarctl.export.mesh import ColouredMesh, DensityGrid, NoSurfaceError, VertexColourFn, marching_cubes, \
    mesh_pieces
from avatarctl.geometry.cameras import Camera

LEVEL_STEP = float(np.sqrt(2.0))  # factor between neighbouring candidates (a 2x ladder skipped the demo's best level)
LEVEL_STEPS = 4  # candidates reach LEVEL_STEP^4 = 4x either side of the body level
SCORE_VIEWS = 3  # training views scored (spread over the project's training views)
SCORE_MAX_SIDE = 256  # pixels: larger scoring images are scaled down


@dataclass(frozen=True)
class ScoringImage:
    """One training photograph the candidate meshes are scored against (eval bbox protocol)."""

    view: str
    camera: Camera  # pinhole, of the image's own size (scaled down by `scoring_image` when larger)
    target: np.ndarray  # [H, W, 3] float32 in [0, 1]: the photograph over the fit's background
    region: np.ndarray  # [H, W] bool: the pixels scored (the body's bbox, eval `bbox` protocol)

    def __post_init__(self) -> None:
        H, W = self.camera.height, self.camera.width
        assert self.target.shape == (H, W, 3), f"target: expected [{H}, {W}, 3], got {self.target.shape}"
        assert self.region.shape == (H, W), f"region: expected [{H}, {W}], got {self.region.shape}"


@dataclass(frozen=True)
class LevelScore:
    """One candidate level and what it showed in the scoring images."""

    step: int  # k: level = body level * LEVEL_STEP^k
    level: float  # 1/metre
    psnr: float | None  # dB, mean over the scoring images; None: no surface at this level
    faces: int
    pieces: int  # connected pieces (after dropping the small ones)
    largest_piece: float  # the largest piece's share of the faces
    baked: int  # vertices coloured to score it (those of the faces hit)


@dataclass(frozen=True)
class LevelChoice:
    """The outcome of `choose_level`."""

    body_level: float  # b, 1/metre (`mesh.body_level`)
    step: int  # the chosen candidate's k
    level: float  # the chosen level, 1/metre
    factor: float  # level / b: what the other meshes of the export (other frames, the rest pose) multiply their b by
    candidates: tuple[LevelScore, ...]  # in the order scored
    views: tuple[str, ...]  # the scoring images' views
    seconds: float  # the search (not the rest of the chosen mesh's bake)


def pick_views(views: Sequence[str], count: int = SCORE_VIEWS) -> list[str]:
    """`count` of `views` spread evenly over the list (its first and last included), all of them when fewer."""
    if len(views) <= count:
        return list(views)
    return [views[i] for i in sorted(set(np.linspace(0, len(views) - 1, count).round().astype(int).tolist()))]


def scoring_image(view: str, camera: Camera, rgb: np.ndarray, mask: np.ndarray,
                  background: tuple[float, float, float], body_vertices: np.ndarray,
                  max_side: int = SCORE_MAX_SIDE) -> ScoringImage:
    """A training photograph made ready for scoring: rgb [H, W, 3] (uint8 or float) and mask [H, W] of `camera`'s
    (undistorted) image, composited over `background` (`evaluate.protocols.ground_truth`); scaled down (area average,
    `Camera.scaled`) when its long side exceeds `max_side`; the region is the eval bbox of the posed body's vertices
    [V, 3] (world, metres)."""
    import cv2

    from avatarctl.evaluate.protocols import bbox_region, ground_truth

    cam = camera.pinhole()
    target = ground_truth(rgb, mask, background)
    scale = min(1.0, max_side / max(cam.width, cam.height))
    if scale < 1.0:
        cam = cam.scaled(scale)
        target = cv2.resize(target, (cam.width, cam.height), interpolation=cv2.INTER_AREA)
    region = bbox_region(cam, np.asarray(body_vertices, np.float64)).mask.astype(bool)
    return ScoringImage(view=view, camera=cam, target=np.asarray(target, np.float32), region=region)


@dataclass
class _Candidate:
    """A candidate mesh, its colours valid where the scoring images see it."""

    mesh: ColouredMesh  # colours valid where `baked`
    baked: np.ndarray  # [verts] bool: at least the vertices seen (all, for a colouring that does all at once)


def choose_level(grid: DensityGrid, body_level: float, colour: VertexColourFn, images: Sequence[ScoringImage],
                 background: tuple[float, float, float], min_component: float = 0.01,
                 step: float = LEVEL_STEP, steps: int = LEVEL_STEPS) -> tuple[LevelChoice, ColouredMesh]:
    """The level of the best candidate (module docstring) -> (the choice, the mesh at that level, fully coloured).

    grid: the density refined around `body_level` (1/metre); colour and min_component as for `mesh.extract_mesh`;
    background: the scoring images' (the fit's); images: at least one. Raises `NoSurfaceError` when no candidate has
    a surface.
    """
    if not images:
        raise ValueError("choose_level needs at least one scoring image")
    if not body_level > 0:
        raise ValueError(f"body level must be > 0 (1/metre), got {body_level}")
    from avatarctl.evaluate.metrics import psnr
    from avatarctl.export.raster import cast_pixels, shade
    from avatarctl.geometry.raycast import RayCaster

    t0 = time.perf_counter()
    scores: dict[int, LevelScore] = {}
    kept: dict[int, _Candidate] = {}

    def score(k: int) -> float:
        level = body_level * step ** k
        try:
            verts, faces, normals = marching_cubes(grid, level, min_component)
        except NoSurfaceError:
            scores[k] = LevelScore(step=k, level=round(level, 4), psnr=None, faces=0, pieces=0, largest_piece=0.0,
                                   baked=0)
            return float("-inf")
        caster = RayCaster(verts, faces)
        hits = [cast_pixels(caster, im.camera) for im in images]
        seen = np.zeros(verts.shape[0], bool)
        for h in hits:
            seen[faces[h.face].ravel()] = True
        colours, done = colour(verts, faces, normals, seen)
        mesh = ColouredMesh(vertices=verts, faces=faces, normals=normals, colours=np.asarray(colours, np.float32))
        value = float(np.mean([psnr(shade(mesh, h, background).rgb, im.target, im.region)
                               for h, im in zip(hits, images)]))
        pieces, largest = mesh_pieces(faces, verts.shape[0])
        scores[k] = LevelScore(step=k, level=round(level, 4), psnr=round(value, 4), faces=int(faces.shape[0]),
                               pieces=pieces, largest_piece=round(largest, 4), baked=int(seen.sum()))
        kept[k] = _Candidate(mesh=mesh, baked=done)
        return value

    best = search_steps(score, steps)
    if scores[best].psnr is None:
        raise NoSurfaceError(f"no candidate level from {body_level / step ** steps:.3g} to "
                             f"{body_level * step ** steps:.3g}/m gives a surface")
    seconds = time.perf_counter() - t0
    chosen = kept[best]
    rest = ~chosen.baked
    colours = chosen.mesh.colours.copy()
    if rest.any():
        m = chosen.mesh
        colours[rest] = colour(m.vertices, m.faces, m.normals, rest)[0][rest]
    level = body_level * step ** best
    choice = LevelChoice(body_level=round(body_level, 4), step=best, level=round(level, 4), factor=step ** best,
                         candidates=tuple(scores.values()), views=tuple(im.view for im in images),
                         seconds=round(seconds, 3))
    mesh = ColouredMesh(vertices=chosen.mesh.vertices, faces=chosen.mesh.faces, normals=chosen.mesh.normals,
                        colours=colours)
    return choice, mesh


def search_steps(score: Callable[[int], float], steps: int) -> int:
    """The step k in [-steps, steps] the search of the module docstring (step 2) ends on: `score(k)` (higher is
    better) of k = 0, -1, +1, then one step at a time from the better neighbour while the score strictly improves.
    Each k is scored once."""
    seen = {k: score(k) for k in (0, -1, 1)} if steps >= 1 else {0: score(0)}
    best = 0
    for k in (-1, 1):
        if k in seen and seen[k] > seen[best]:
            best = k
    if best == 0:
        return 0
    d = best
    while abs(best + d) <= steps:
        value = score(best + d)
        if not value > seen[best]:
            break
        seen[best + d] = value
        best += d
    return best
