"""Appearance of the synthetic scene: procedural textures, Lambert shading, and the background environment.

Textures are solid (3D) functions of a surface point's *canonical* coordinates, so detail stays attached to the
surface whatever the pose: the body uses its rest-pose position (metres), the skirt its grid parameters (angle
around the body, height fraction). Regions of the body (skin, top, hair, shoes, eyes, legs) come from each
vertex's dominant skinning bone. Shading: albedo x (ambient + sum of world-fixed directional lights x max(0, n.l)),
colours in [0, 1] (written as sRGB without further transfer). The background is an environment (a floor plane at
the feet and a cylindrical wall, radius 6 m, centred on the origin), so it is geometrically consistent across
cameras and distorted by the lens like everything else; rendering it without the subject gives the clean plate.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

SKIN, TOP, HAIR, SHOES, EYES, LEGS = range(6)
WALL_RADIUS = 6.0
LIGHTS = ((np.array([0.45, -0.8, 0.9]), 0.75), (np.array([-0.7, 0.35, 0.35]), 0.3), (np.array([0.1, 0.9, 0.5]), 0.2))
AMBIENT = 0.3


def _hash3(i: np.ndarray, j: np.ndarray, k: np.ndarray, seed: float) -> np.ndarray:
    """Deterministic lattice hash in [0, 1) for integer lattice coordinates (float arrays)."""
    h = np.sin(i * 127.1 + j * 311.7 + k * 74.7 + seed * 0.618) * 43758.5453
    return h - np.floor(h)


def value_noise(p: np.ndarray, scale: float, seed: float) -> np.ndarray:
    """Smooth value noise in [0, 1): p [N, 3] (metres or any unit) with lattice spacing 1 / scale -> [N]."""
    q = p * scale
    f = np.floor(q)
    w = q - f
    w = w * w * (3 - 2 * w)
    out = np.zeros(p.shape[0])
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                h = _hash3(f[:, 0] + dx, f[:, 1] + dy, f[:, 2] + dz, seed)
                wt = (w[:, 0] if dx else 1 - w[:, 0]) * (w[:, 1] if dy else 1 - w[:, 1]) * \
                     (w[:, 2] if dz else 1 - w[:, 2])
                out += h * wt
    return out


@dataclass(frozen=True)
class Palette:
    """Seeded colours and pattern choices of one capture."""

    skin: np.ndarray  # [3] RGB in [0, 1]
    hair: np.ndarray
    top_a: np.ndarray
    top_b: np.ndarray
    top_pattern: int  # 0 stripes, 1 checks, 2 dots
    legs_bare: bool
    legs: np.ndarray
    shoes: np.ndarray
    skirt_a: np.ndarray
    skirt_b: np.ndarray
    skirt_c: np.ndarray
    lining: np.ndarray
    wall: np.ndarray
    wall_b: np.ndarray
    floor_a: np.ndarray
    floor_b: np.ndarray
    seed: float

    @classmethod
    def from_seed(cls, seed: int) -> "Palette":
        rng = np.random.default_rng([seed, 3])
        skins = np.array([[0.93, 0.76, 0.64], [0.80, 0.60, 0.46], [0.62, 0.43, 0.31], [0.42, 0.28, 0.20]])
        hairs = np.array([[0.10, 0.07, 0.05], [0.35, 0.22, 0.12], [0.70, 0.55, 0.30], [0.25, 0.25, 0.28]])

        def col(lo: float = 0.15, hi: float = 0.9) -> np.ndarray:
            return lo + (hi - lo) * rng.random(3)

        return cls(skin=skins[rng.integers(4)], hair=hairs[rng.integers(4)], top_a=col(), top_b=col(),
                   top_pattern=int(rng.integers(3)), legs_bare=bool(rng.random() < 0.5), legs=col(0.05, 0.4),
                   shoes=col(0.05, 0.35), skirt_a=col(0.2, 0.95), skirt_b=col(0.05, 0.6), skirt_c=col(0.5, 1.0),
                   lining=col(0.3, 0.6), wall=col(0.45, 0.85), wall_b=col(0.2, 0.7), floor_a=col(0.3, 0.6),
                   floor_b=col(0.15, 0.45), seed=float(rng.integers(1, 10_000)))


def body_regions(bone_labels: list[str], dominant_bone: np.ndarray, rest: np.ndarray) -> np.ndarray:
    """[V] region id per body vertex from its dominant bone and rest position (anny axes, metres)."""
    lab = np.array(bone_labels)[dominant_bone]
    region = np.full(lab.shape, SKIN)
    starts = np.char.startswith
    torso = starts(lab, "spine") | starts(lab, "pelvis") | starts(lab, "root") | starts(lab, "clavicle") | \
        starts(lab, "shoulder") | starts(lab, "upperarm01")
    region[torso] = TOP
    region[starts(lab, "upperleg") | starts(lab, "lowerleg")] = LEGS
    region[starts(lab, "foot") | starts(lab, "toe")] = SHOES
    region[starts(lab, "eye")] = EYES
    head = starts(lab, "head") | starts(lab, "neck") | starts(lab, "eye")
    top = rest[:, 2].max()
    face_y = rest[head, 1].min()
    hair = head & ((rest[:, 2] > top - 0.06) | ((rest[:, 2] > top - 0.24) & (rest[:, 1] > face_y + 0.07)))
    region[hair] = HAIR
    return region


def body_albedo(c: np.ndarray, region: np.ndarray, pal: Palette) -> np.ndarray:
    """Albedo [N, 3] of body points: canonical position c [N, 3] (metres), region [N]."""
    s = pal.seed
    out = np.empty((c.shape[0], 3))
    fine = value_noise(c, 180.0, s)  # ~5 mm grain
    mid = value_noise(c, 30.0, s + 1)
    # skin with mottling and freckles
    skin = pal.skin[None] * (0.92 + 0.1 * mid[:, None] + 0.05 * fine[:, None])
    freckle = value_noise(c, 260.0, s + 2) > 0.8
    skin[freckle] *= 0.85
    out[:] = skin
    m = region == TOP
    if m.any():
        p = c[m]
        if pal.top_pattern == 0:
            band = (np.sin(p[:, 2] * 2 * np.pi * 28) > 0.2)
        elif pal.top_pattern == 1:
            band = (np.sin(p[:, 2] * 2 * np.pi * 20) * np.sin(np.arctan2(p[:, 1], p[:, 0]) * 24) > 0)
        else:
            g = p * 40.0
            band = np.linalg.norm(g - np.round(g), axis=1) < 0.28
        col = np.where(band[:, None], pal.top_a[None], pal.top_b[None])
        out[m] = col * (0.85 + 0.25 * fine[m, None])  # knit grain
    m = region == LEGS
    if m.any() and not pal.legs_bare:
        diamond = (np.abs(np.sin(c[m, 2] * 90)) + np.abs(np.sin(np.arctan2(c[m, 1], c[m, 0]) * 10))) > 1.2
        out[m] = pal.legs[None] * (0.8 + 0.4 * diamond[:, None]) * (0.9 + 0.2 * fine[m, None])
    m = region == HAIR
    out[m] = pal.hair[None] * (0.7 + 0.6 * value_noise(c[m] * np.array([60.0, 60.0, 8.0]), 4.0, s + 3)[:, None])
    m = region == SHOES
    out[m] = pal.shoes[None] * (0.8 + 0.4 * fine[m, None])
    m = region == EYES
    out[m] = np.array([0.08, 0.06, 0.05])
    return np.clip(out, 0.0, 1.0)


def skirt_albedo(theta: np.ndarray, h: np.ndarray, inside: np.ndarray, pal: Palette) -> np.ndarray:
    """Albedo [N, 3] of skirt points: angle theta [N] (radians), height fraction h [N] (0 waist .. 1 hem),
    inside [N] bool (the lining seen from within)."""
    s = pal.seed
    x = theta * 0.45 / (2 * np.pi) * 2 * np.pi  # ~arc length in metres at a 0.45 m mean radius
    y = h * 0.75
    p = np.stack([np.cos(theta) * 3, np.sin(theta) * 3, h * 4], -1)
    # tartan: two stripe families in each direction
    sx = (np.sin(x * 2 * np.pi * 9) > 0.55) | (np.sin(x * 2 * np.pi * 27) > 0.85)
    sy = (np.sin(y * 2 * np.pi * 9) > 0.55) | (np.sin(y * 2 * np.pi * 27) > 0.85)
    col = np.where((sx & sy)[:, None], pal.skirt_c[None],
                   np.where((sx | sy)[:, None], pal.skirt_b[None], pal.skirt_a[None]))
    # small flowers: dots on a staggered grid
    gx, gy = x * 14, y * 14 + 0.5 * np.floor(x * 14)
    dot = (gx - np.round(gx)) ** 2 + (gy - np.round(gy)) ** 2 < 0.04
    col = np.where(dot[:, None], pal.skirt_c[None] * 0.5 + 0.5, col)
    col = np.where((h > 0.93)[:, None] | (h < 0.03)[:, None], pal.skirt_b[None] * 0.6, col)  # hem and waistband
    col = col * (0.88 + 0.22 * value_noise(p, 60.0, s + 4)[:, None])  # weave
    col = np.where(inside[:, None], pal.lining[None] * (0.9 + 0.1 * value_noise(p, 30.0, s + 5)[:, None]), col)
    return np.clip(col, 0.0, 1.0)


def lambert(albedo: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """albedo [N, 3], unit normals [N, 3] (world, facing the viewer) -> colour [N, 3] in [0, 1]."""
    light = np.full(normal.shape[0], AMBIENT)
    for d, w in LIGHTS:
        light += w * np.clip(normal @ (d / np.linalg.norm(d)), 0.0, None)
    return np.clip(albedo * light[:, None], 0.0, 1.0)


def environment(origin: np.ndarray, dirs: np.ndarray, floor_z: float, pal: Palette) -> np.ndarray:
    """Background colour [N, 3] seen along rays (origin [3], dirs [N, 3]): floor plane z=floor_z, wall r=6 m."""
    o = np.asarray(origin, dtype=np.float64)
    d = dirs.astype(np.float64)
    s = pal.seed
    # wall: |o_xy + t d_xy| = R
    a = (d[:, :2] ** 2).sum(1)
    b = 2 * (d[:, :2] @ o[:2])
    c = (o[:2] ** 2).sum() - WALL_RADIUS ** 2
    t_wall = (-b + np.sqrt(np.maximum(b * b - 4 * a * c, 0.0))) / (2 * np.maximum(a, 1e-12))
    with np.errstate(divide="ignore", invalid="ignore"):
        t_floor = np.where(d[:, 2] < -1e-6, (floor_z - o[2]) / d[:, 2], np.inf)
    floor = t_floor < t_wall
    t = np.where(floor, t_floor, t_wall)
    p = o[None] + t[:, None] * d
    out = np.empty((d.shape[0], 3))
    # wall: wallpaper stripes, panels and grain; darker towards the top
    ang = np.arctan2(p[:, 1], p[:, 0])
    stripes = np.sin(ang * 90) > 0.6
    panel = (np.sin(ang * 5 + s) > 0.7) & (np.abs(p[:, 2] - 0.6) < 0.5)
    wall = np.where(stripes[:, None], pal.wall[None] * 0.85, pal.wall[None])
    wall = np.where(panel[:, None], pal.wall_b[None], wall)
    wall = wall * (0.9 + 0.15 * value_noise(p, 8.0, s + 6)[:, None]) * \
        np.clip(1.05 - 0.12 * (p[:, 2] - floor_z), 0.6, 1.0)[:, None]
    out[:] = wall
    # floor: planks along x with grain, a darker ring under the subject
    fp = p[floor]
    plank = np.floor(fp[:, 1] / 0.18)
    grain = value_noise(np.stack([fp[:, 0] * 2, fp[:, 1] * 40, plank], -1), 3.0, s + 7)
    base = np.where((plank % 2 == 0)[:, None], pal.floor_a[None], pal.floor_b[None])
    seam = np.abs(fp[:, 1] / 0.18 - np.round(fp[:, 1] / 0.18)) < 0.04
    col = base * (0.8 + 0.4 * grain[:, None])
    col[seam] *= 0.6
    col *= np.clip(0.55 + 0.15 * np.linalg.norm(fp[:, :2], axis=1), 0.55, 1.0)[:, None]
    out[floor] = col
    return np.clip(out, 0.0, 1.0)
