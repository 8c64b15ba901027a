"""`synthesize`: a ground-truth multi-view capture of an anny body in a simulated skirt, in EasyMocap layout.

Steps: procedural motion (`synth.motion`) -> anny forward kinematics for every simulated frame -> XPBD skirt
simulation against the body mesh (`synth.garment`) -> cameras on a ring with lens distortion -> ray-cast
rendering of body + skirt over an environment (`synth.raster`, `synth.shade`) -> files. The whole output
directory is built in a temporary sibling and renamed at the end (`avatarctl.atomic.atomic_dir`).

Layout written (see docs/formats.md)::

    OUT/intri.yml, OUT/extri.yml        cameras (cv2.FileStorage; K, dist k1 k2 p1 p2 k3, H, W; R, Rot, T metres)
    OUT/images/<cam>/<frame:06d>.jpg    distorted RGB images
    OUT/masks/<cam>/<frame:06d>.png     ground-truth foreground masks (0 / 255, subpixel coverage >= 0.5)
    OUT/background/<cam>.jpg            clean background plates
    OUT/motion.npz                      anny fits (loadable by `avatarctl.body.motion.BodyMotion.load`); with
                                        `fit_noise_*` > 0 perturbed like real fits (`body.perturb`)
    OUT/gt/motion.npz                   the true fits, when motion.npz was perturbed or left out (`fits` "none")
    OUT/gt/masks/<cam>/<frame:06d>.png  the true masks, when masks/ was left out (`masks` "none")
    OUT/split.json                      train/test frames and views (test views are never trained on; with
                                        `train_views` k > 0 only cam00..k-1 train, e.g. the monocular preset)
    OUT/gt/geometry.npz                 per-frame body and skirt vertices, faces, skirt grid parameters
    OUT/capture.json                    generator version, config, seed, timings, statistics
    OUT/contact_sheet.png               a few frames x views for a person to look at

The imperfections of a real camera (`SynthConfig.imperfections`, `synth.imperfections`) act on the images and plates
only: colour gains per camera (recorded in capture.json "camera_colour"), sensor noise, JPEG quality, motion blur.
capture.json records them and the config of the clean twin (`SynthConfig.clean_twin`: same seed, same scene).

With `layout = "video"` (the `phone` preset: what one phone gives a user) OUT holds only::

    OUT/video.mp4                       the first camera's frames (H.264, undistorted lens, frame rate
                                        sim_fps / stride), its 35 mm-equivalent focal length in the metadata tag
                                        `FOCAL_35MM_TAG` (as an iPhone writes it)
    OUT/gt/capture/                     the truth: the same render as the EasyMocap capture above (every camera,
                                        calibration, masks, plates, exact fits, split, gt/geometry.npz)
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from avatarctl.atomic import write_image
from avatarctl.errors import InputError
from avatarctl.geometry.cameras import Camera, look_at
from avatarctl.io.gt_geometry import GT_GEOMETRY, GT_MOTION
from avatarctl.progress import ProgressFn, ProgressReport
from avatarctl.synth.config import BLUR_SAMPLES, GENERATOR_VERSION, SynthConfig
from avatarctl.synth.imperfections import camera_gains, noise_rng, plate_rng, sensor_image, shutter_offsets
from avatarctl.synth.motion import PHENOTYPE_LABELS, ProceduralMotion, make_motion

VIDEO_FILE = "video.mp4"  # layout "video": the one file a user has
GT_CAPTURE = Path("gt") / "capture"  # layout "video": the truth, as an EasyMocap capture
GT_MASKS = Path("gt") / "masks"  # masks "none": the true masks, where ingest does not look
FOCAL_35MM_TAG = "com.apple.quicktime.camera.focal_length.35mm_equivalent"  # the focal length phones record
FULL_FRAME_DIAGONAL_MM = 43.27  # diagonal of a 36 x 24 mm frame: f_35mm / 43.27 = f_px / image diagonal (px)


@dataclass(frozen=True)
class SynthResult:
    """What `synthesize` wrote."""

    out: Path
    cameras: list[Camera]
    train_frames: list[int]
    test_frames: list[int]
    train_views: list[str]
    test_views: list[str]
    timings: dict[str, float]  # seconds per step
    hem_pair: dict | None  # two training frames with near-identical body pose and different hem
    max_penetrating_particles: int  # skirt particles > 2 mm inside the body, worst simulated frame
    hem_radius_range: tuple[float, float] = field(default=(0.0, 0.0))  # metres, over written frames

    @property
    def sheet(self) -> Path:
        """The contact sheet (under gt/capture/ for the video layout)."""
        return (self.out / GT_CAPTURE if (self.out / VIDEO_FILE).is_file() else self.out) / "contact_sheet.png"


@dataclass(frozen=True)
class Scene:
    """Geometry of the written frames."""

    body_vertices: np.ndarray  # [frames, Vb, 3] float32 world metres
    skirt_vertices: np.ndarray  # [frames, P, 3] float32
    body_faces: np.ndarray  # [Fb, 3] int32, outward normals
    skirt_faces: np.ndarray  # [Fs, 3] int32
    body_rest: np.ndarray  # [Vb, 3] canonical (rest) body vertices, texture coordinates
    body_region: np.ndarray  # [Vb] region id (synth.shade)
    skirt_param: np.ndarray  # [P, 2] (angle, height fraction)
    skirt_hem: np.ndarray  # [segments] particle indices
    floor_z: float


def load_scene(out: Path) -> Scene:
    """The ground-truth `Scene` of a written capture (from `gt/geometry.npz` and `capture.json`), e.g. to
    re-render it through other cameras."""
    out = Path(out)
    with np.load(out / GT_GEOMETRY) as z:
        g = {k: z[k] for k in z.files}
    info = json.loads((out / "capture.json").read_text())
    return Scene(body_vertices=g["body_vertices"], skirt_vertices=g["garment_vertices"], body_faces=g["body_faces"],
                 skirt_faces=g["garment_faces"], body_rest=g["body_rest_vertices"],
                 body_region=g["body_region"].astype(np.int64), skirt_param=g["garment_param"].astype(np.float64),
                 skirt_hem=g["garment_hem"], floor_z=float(info["floor_z"]))


def make_cameras(config: SynthConfig, target_z: float) -> list[Camera]:
    """`config.views` cameras on a ring around the origin, jittered by the seed, with k1/k2 lens distortion (none for
    the video layout: a phone corrects its lens in the video)."""
    rng = np.random.default_rng([config.seed, 4])
    n, size, width = config.views, config.size, config.image_width
    cams = []
    for i in range(n):
        az = 2 * np.pi * i / n + rng.uniform(-0.25, 0.25) * 2 * np.pi / n - np.pi / 2  # cam00 in front (-y)
        dist = rng.uniform(2.9, 3.4)
        eye = np.array([dist * np.cos(az), dist * np.sin(az), rng.uniform(-0.1, 0.6)])
        target = np.array([rng.uniform(-0.03, 0.03), rng.uniform(-0.03, 0.03), target_z + rng.uniform(-0.04, 0.04)])
        R, T = look_at(eye, target)
        half_extent = 1.0  # metres visible above and below the target at the camera distance
        f = (size / 2) * np.linalg.norm(eye - target) / half_extent * rng.uniform(0.97, 1.03)
        cx = (width - 1) / 2 + rng.uniform(-0.02, 0.02) * width
        cy = (size - 1) / 2 + rng.uniform(-0.02, 0.02) * size
        K = np.array([[f, 0, cx], [0, f * rng.uniform(0.995, 1.005), cy], [0, 0, 1]])
        k1 = rng.choice([-1.0, 1.0]) * rng.uniform(0.12, 0.3)  # ~1-5 px at the image corners at 96 px
        k2 = rng.uniform(-0.05, 0.05)
        if config.layout == "video":
            k1 = k2 = 0.0
        cams.append(Camera(name=f"cam{i:02d}", K=K, R=R, T=T, width=width, height=size,
                           dist=np.array([k1, k2, 0.0, 0.0, 0.0])))
    return cams


def split_views(names: list[str], train_views: int = 0) -> tuple[list[str], list[str]]:
    """(train, test) cameras: with `train_views` 0 every third camera (cam01, cam04, ...) is held out for novel-view
    testing; with k > 0 the first k train and all the others are evaluation-only (the monocular preset)."""
    if train_views > 0:
        return list(names[:train_views]), list(names[train_views:])
    test = [n for i, n in enumerate(names) if i % 3 == 1]
    return [n for n in names if n not in test], test


def _check_out(out: Path) -> None:
    if out.exists() and not out.is_dir():
        raise InputError("output path exists and is a file", where=str(out), fix="choose a new OUT directory")
    if out.is_dir() and any(out.iterdir()):
        raise InputError("output directory is not empty", where=str(out),
                         fix="choose a new OUT directory or delete this one")


def _anny_forward(motion: ProceduralMotion, model, chunk: int = 128) -> np.ndarray:
    """[rows, V, 3] float32 posed anny vertices for every row of the timeline."""
    import torch

    pheno = torch.tensor(motion.phenotype, dtype=torch.float64)[None]
    kw = {lab: pheno[:, i] for i, lab in enumerate(PHENOTYPE_LABELS)}
    out = []
    with torch.no_grad():
        for s in range(0, motion.rows, chunk):
            pp = torch.as_tensor(motion.pose_parameters[s:s + chunk], dtype=torch.float64)
            out.append(model(pose_parameters=pp, phenotype_kwargs=kw)["vertices"].float().numpy())
    return np.concatenate(out)


def _hem_pair(body: np.ndarray, hem: np.ndarray, frames: list[int]) -> dict | None:
    """Among `frames`, the pair with body-vertex RMS distance < 5 mm whose hem rings differ the most."""
    sub = body[frames][:, ::7].reshape(len(frames), -1).astype(np.float64)  # [n, 3 * V/7]
    h = hem[frames].reshape(len(frames), -1).astype(np.float64)
    nb, nh = sub.shape[1] / 3, h.shape[1] / 3
    sq = (sub ** 2).sum(1)
    db = np.sqrt(np.maximum(sq[:, None] + sq[None] - 2 * sub @ sub.T, 0.0) / nb)
    hq = (h ** 2).sum(1)
    dh = np.sqrt(np.maximum(hq[:, None] + hq[None] - 2 * h @ h.T, 0.0) / nh)
    ok = (db < 0.005) & (np.arange(len(frames))[:, None] < np.arange(len(frames))[None])
    if not ok.any():
        return None
    score = np.where(ok, dh, -1.0)
    i, j = np.unravel_index(int(score.argmax()), score.shape)
    return {"frames": [int(frames[i]), int(frames[j])], "body_rms_m": float(db[i, j]), "hem_rms_m": float(dh[i, j])}


def simulate(config: SynthConfig, progress: ProgressFn | None = None) -> tuple[Scene, ProceduralMotion, dict]:
    """Motion, body and skirt for every written frame. Returns (scene, motion, stats incl. timings)."""
    from avatarctl.body.anny_model import AnnyBody
    from avatarctl.synth.garment import ClothParams, SkirtSimulator, build_skirt
    from avatarctl.synth.shade import body_regions

    stats: dict = {}
    t0 = time.perf_counter()
    body_model = AnnyBody("cpu")
    model = body_model.model
    labels = list(body_model.joint_names)
    for name, idx in (("lowerarm01.L", 50), ("lowerarm01.R", 76), ("spine05", 41), ("upperleg01.L", 2)):
        if labels[idx] != name:
            raise RuntimeError(f"anny rig changed: bone {idx} is {labels[idx]!r}, expected {name!r}")
    elbow_axes = model.reference_bone_orientations[[50, 76]][:, :, 0].double().numpy()
    motion = make_motion(config, elbow_axes)
    body = _anny_forward(motion, model)  # [rows, V, 3]
    faces = body_model.faces().numpy().astype(np.int32)
    idx = model.vertex_bone_indices.long().numpy()
    dominant = idx[np.arange(idx.shape[0]), model.vertex_bone_weights.numpy().argmax(1)]
    arms_head = ("upperarm", "lowerarm", "wrist", "finger", "metacarpal", "head", "neck", "eye", "clavicle",
                 "shoulder")
    trunk = np.array([not labels[d].startswith(arms_head) for d in dominant])
    stats["anny_s"] = time.perf_counter() - t0

    if config.garment == "none":  # tight clothing: the body alone, nothing to simulate
        return _body_only_scene(config, body, faces, motion, body_model, labels, dominant, stats), motion, stats
    t0 = time.perf_counter()
    skirt = build_skirt(body[0], faces, trunk, config.skirt_rings, config.skirt_segments)
    reach = np.array([not labels[d].startswith(("head", "neck", "eye", "foot", "toe")) for d in dominant])
    sim = SkirtSimulator(skirt, body[0], faces, config.sim_fps,
                         ClothParams(substeps=config.substeps, iterations=config.iterations), collide_vertices=reach)
    written = {int(r): k for k, r in enumerate(motion.written_rows)}
    skirt_x = np.empty((config.frames, skirt.num_particles, 3), dtype=np.float32)
    worst = 0
    for r in range(1, motion.rows):
        x = sim.step(body[r])
        if r in written:
            skirt_x[written[r]] = x
            worst = max(worst, sim.count_penetrations())
        if progress:
            progress(ProgressReport(done=r, total=motion.rows - 1, part="simulate"))
    stats["simulate_s"] = time.perf_counter() - t0
    stats["simulate_s_per_frame"] = stats["simulate_s"] / max(motion.rows - 1, 1)
    stats["max_penetrating_particles"] = worst

    rest = body_model.run(_first_motion(motion))["rest_vertices"].float().numpy()
    body_w = body[motion.written_rows]
    scene = Scene(body_vertices=body_w, skirt_vertices=skirt_x, body_faces=sim.body_faces, skirt_faces=skirt.faces,
                  body_rest=rest, body_region=body_regions(labels, dominant, rest),
                  skirt_param=skirt.param.astype(np.float32).astype(np.float64),
                  skirt_hem=skirt.hem, floor_z=float(body[:, :, 2].min()) - 0.002)
    return scene, motion, stats


def _body_only_scene(config: SynthConfig, body: np.ndarray, faces: np.ndarray, motion: ProceduralMotion, body_model,
                     labels: list[str], dominant: np.ndarray, stats: dict) -> Scene:
    """The `Scene` of a capture without garment: the skirt arrays are empty ([frames, 0, 3], [0, 3], ...)."""
    from avatarctl.synth.geometry import signed_volume
    from avatarctl.synth.shade import body_regions

    faces = np.ascontiguousarray(faces if signed_volume(body[0].astype(np.float64), faces) >= 0 else faces[:, ::-1])
    stats.update(simulate_s=0.0, simulate_s_per_frame=0.0, max_penetrating_particles=0)
    rest = body_model.run(_first_motion(motion))["rest_vertices"].float().numpy()
    return Scene(body_vertices=body[motion.written_rows], skirt_vertices=np.zeros((config.frames, 0, 3), np.float32),
                 body_faces=faces, skirt_faces=np.zeros((0, 3), np.int32), body_rest=rest,
                 body_region=body_regions(labels, dominant, rest), skirt_param=np.zeros((0, 2)),
                 skirt_hem=np.zeros(0, np.int64), floor_z=float(body[:, :, 2].min()) - 0.002)


def _first_motion(motion: ProceduralMotion):
    from avatarctl.body.motion import BodyMotion

    return BodyMotion(body_model="anny", frame_index=np.array([0]), pose_parameters=motion.pose_parameters[:1],
                      phenotype=motion.phenotype, phenotype_labels=PHENOTYPE_LABELS)


class SceneRenderer:
    """Renders `Scene` frames through distorted cameras (ray casting + shading + environment background)."""

    def __init__(self, scene: Scene, cameras: list[Camera], ss: int, seed: int):
        from avatarctl.geometry.raycast import RayCaster
        from avatarctl.synth.raster import camera_rays
        from avatarctl.synth.shade import Palette, environment

        self.scene = scene
        self.cameras = cameras
        self.ss = ss
        self.pal = Palette.from_seed(seed)
        self.nb_v = scene.body_vertices.shape[1]
        self.nb_f = scene.body_faces.shape[0]
        self.faces = np.concatenate([scene.body_faces, scene.skirt_faces + self.nb_v]).astype(np.int64)
        self.caster = RayCaster(self._verts(0), self.faces)
        self.grids = [camera_rays(c, ss) for c in cameras]
        self.bg = [environment(g.origin, g.dirs.reshape(-1, 3), scene.floor_z, self.pal).reshape(g.dirs.shape)
                   .astype(np.float32) for g in self.grids]

    def _verts(self, k: int) -> np.ndarray:
        return np.concatenate([self.scene.body_vertices[k], self.scene.skirt_vertices[k]])

    def plate(self, c: int) -> np.ndarray:
        """[H, W, 3] float32 clean background of camera c."""
        return _downsample(self.bg[c], self.ss)

    def render_frame(self, k: int, cams: list[int] | None = None, offsets: np.ndarray | None = None,
                     segment: tuple[int, int] | None = None) -> list[tuple[np.ndarray, np.ndarray]]:
        """Written frame k -> per camera (image [H, W, 3] float32 in [0, 1], coverage [H, W] float32). With
        `offsets` (times in written-frame units, `imperfections.shutter_offsets`; 0 among them) the image is the mean
        of the renders at k + offset (motion blur; the geometry interpolated within `segment`), the coverage the
        frame's own (offset 0)."""
        if offsets is None or len(offsets) == 1:
            return self._render_vertices(self._verts(k), cams)
        from avatarctl.synth.imperfections import shutter_vertices

        assert segment is not None and 0.0 in offsets, "a blurred render needs its segment and the offset 0"
        sums, cover = None, None
        for tau in offsets:
            verts = np.concatenate([shutter_vertices(self.scene.body_vertices, k, float(tau), segment),
                                    shutter_vertices(self.scene.skirt_vertices, k, float(tau), segment)])
            views = self._render_vertices(verts, cams)
            sums = [img for img, _ in views] if sums is None else [a + img for a, (img, _) in zip(sums, views)]
            if tau == 0.0:
                cover = [cov for _, cov in views]
        assert sums is not None and cover is not None
        return [(a / len(offsets), cov) for a, cov in zip(sums, cover)]

    def _render_vertices(self, verts: np.ndarray, cams: list[int] | None) -> list[tuple[np.ndarray, np.ndarray]]:
        """The scene with body + skirt vertices `verts` [Vb + P, 3] -> per camera (image, coverage)."""
        from avatarctl.geometry.normals import vertex_normals

        normals = vertex_normals(verts.astype(np.float64), self.faces)
        self.caster.update(verts)
        out = []
        for c in (range(len(self.cameras)) if cams is None else cams):
            cam, grid, ss = self.cameras[c], self.grids[c], self.ss
            uv = cam.project(verts)
            x0 = int(np.clip(np.floor(uv[:, 0].min()) - 2, 0, cam.width)) * ss
            x1 = int(np.clip(np.ceil(uv[:, 0].max()) + 3, 0, cam.width)) * ss
            y0 = int(np.clip(np.floor(uv[:, 1].min()) - 2, 0, cam.height)) * ss
            y1 = int(np.clip(np.ceil(uv[:, 1].max()) + 3, 0, cam.height)) * ss
            img = self.bg[c].copy()
            hit_full = np.zeros(img.shape[:2], dtype=np.float32)
            if x1 > x0 and y1 > y0:
                dirs = grid.dirs[y0:y1, x0:x1].reshape(-1, 3)
                face, t = self.caster.cast(grid.origin, dirs)
                hit = face >= 0
                sub = img[y0:y1, x0:x1].reshape(-1, 3)
                if hit.any():
                    sub[hit] = self._shade(face[hit], t[hit], dirs[hit], grid.origin, verts, normals)
                img[y0:y1, x0:x1] = sub.reshape(y1 - y0, x1 - x0, 3)
                hit_full[y0:y1, x0:x1] = hit.reshape(y1 - y0, x1 - x0)
            out.append((_downsample(img, ss), _downsample(hit_full[..., None], ss)[..., 0]))
        return out

    def _shade(self, face: np.ndarray, t: np.ndarray, d: np.ndarray, origin: np.ndarray, verts: np.ndarray,
               normals: np.ndarray) -> np.ndarray:
        from avatarctl.synth.shade import body_albedo, lambert, skirt_albedo

        tri = self.faces[face]  # [N, 3]
        d = d.astype(np.float64)
        p = origin[None] + t[:, None].astype(np.float64) * d
        a, b, c = (verts[tri[:, i]].astype(np.float64) for i in range(3))
        bary = _barycentric(p, a, b, c)  # [N, 3]
        n = np.einsum("nk,nkd->nd", bary, normals[tri])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        n = np.where((np.einsum("nd,nd->n", n, d) > 0)[:, None], -n, n)
        albedo = np.empty((face.shape[0], 3))
        is_body = face < self.nb_f
        if is_body.any():
            tb, wb = tri[is_body], bary[is_body]
            can = np.einsum("nk,nkd->nd", wb, self.scene.body_rest[tb])
            region = self.scene.body_region[tb[np.arange(tb.shape[0]), wb.argmax(1)]]
            albedo[is_body] = body_albedo(can, region, self.pal)
        sk = ~is_body
        if sk.any():
            ts, ws = tri[sk] - self.nb_v, bary[sk]
            prm = self.scene.skirt_param[ts]  # [N, 3, 2]
            cs = np.einsum("nk,nk->n", ws, np.cos(prm[..., 0]))
            sn = np.einsum("nk,nk->n", ws, np.sin(prm[..., 0]))
            h = np.einsum("nk,nk->n", ws, prm[..., 1])
            geo_n = np.cross(b[sk] - a[sk], c[sk] - a[sk])
            inside = np.einsum("nd,nd->n", geo_n, d[sk]) > 0
            albedo[sk] = skirt_albedo(np.arctan2(sn, cs) % (2 * np.pi), h, inside, self.pal)
        return lambert(albedo, n).astype(np.float32)


def _barycentric(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Barycentric weights [N, 3] of points p [N, 3] in triangles (a, b, c) [N, 3] each, clipped to the triangle."""
    v0, v1, v2 = b - a, c - a, p - a
    d00 = (v0 * v0).sum(1)
    d01 = (v0 * v1).sum(1)
    d11 = (v1 * v1).sum(1)
    d20 = (v2 * v0).sum(1)
    d21 = (v2 * v1).sum(1)
    den = np.maximum(d00 * d11 - d01 * d01, 1e-20)
    v = (d11 * d20 - d01 * d21) / den
    w = (d00 * d21 - d01 * d20) / den
    bary = np.clip(np.stack([1 - v - w, v, w], -1), 0.0, 1.0)
    return bary / np.maximum(bary.sum(1, keepdims=True), 1e-12)


def _downsample(img: np.ndarray, ss: int) -> np.ndarray:
    """Box-filter [H*ss, W*ss, C] -> [H, W, C]."""
    if ss == 1:
        return img
    H, W, C = img.shape[0] // ss, img.shape[1] // ss, img.shape[2]
    return img.reshape(H, ss, W, ss, C).mean(axis=(1, 3))


def _to_u8(img: np.ndarray) -> np.ndarray:
    return np.clip(np.round(img * 255.0), 0, 255).astype(np.uint8)


def synthesize(out: Path, config: SynthConfig, progress: ProgressFn | None = None) -> SynthResult:
    """Generate the capture described by `config` into `out` (which must not exist or be empty).

    Deterministic in `config.seed`: the same seed gives byte-identical files (capture.json differs only in its
    `timings`). Raises `InputError` for a non-empty `out`; nothing is left behind on failure.
    """
    import cv2

    from avatarctl.atomic import atomic_dir
    from avatarctl.body.motion import BodyMotion
    from avatarctl.io.easymocap import write_easymocap_cameras
    from avatarctl.synth.contact_sheet import contact_sheet

    out = Path(out)
    _check_out(out)
    t_all = time.perf_counter()
    scene, motion, stats = simulate(config, progress)
    cameras = make_cameras(config, target_z=-0.06)
    names = [c.name for c in cameras]
    train_views, test_views = split_views(names, config.train_views)
    frames = list(range(config.frames))
    train_frames, test_frames = frames[:config.train_frames], frames[config.train_frames:]
    hem = scene.skirt_vertices[:, scene.skirt_hem]
    centre = scene.body_vertices.mean(1)  # [frames, 3]
    if config.garment == "none":
        hem_radius, hem_pair = np.zeros(config.frames), None
    else:
        hem_radius = np.linalg.norm(hem[..., :2] - centre[:, None, :2], axis=-1).mean(1)  # [frames]
        hem_pair = _hem_pair(scene.body_vertices, hem, train_frames) if len(train_frames) > 1 else None

    gains = camera_gains(config.seed, len(cameras), config.exposure_ev, config.white_balance)  # [cams, 3]
    gains[[names.index(v) for v in test_views]] *= 2.0 ** config.held_out_ev
    offsets = shutter_offsets(config.shutter_s, config.stride / config.sim_fps, BLUR_SAMPLES)
    with atomic_dir(out) as root:
        t0 = time.perf_counter()
        tmp = root / GT_CAPTURE if config.layout == "video" else root
        video = _VideoWriter(root / VIDEO_FILE, cameras[0], motion.fps) if config.layout == "video" else None
        write_easymocap_cameras(tmp, cameras)
        renderer = SceneRenderer(scene, cameras, config.supersample, config.seed)
        jpeg = [int(cv2.IMWRITE_JPEG_QUALITY), config.jpeg_quality]
        masks_dir = tmp / ("masks" if config.masks == "truth" else GT_MASKS)
        (tmp / "background").mkdir()
        for c, cam in enumerate(cameras):
            plate = sensor_image(renderer.plate(c), gains[c], config.noise_std, plate_rng(config.seed, c))
            write_image(tmp / "background" / f"{cam.name}.jpg", _to_u8(plate)[..., ::-1], jpeg)
            (tmp / "images" / cam.name).mkdir(parents=True)
            (masks_dir / cam.name).mkdir(parents=True)
        sheet_frames = _sheet_frames(config, hem_radius, hem_pair)
        sheet_tiles: dict[tuple[int, int], np.ndarray] = {}
        for k in frames:
            segment = (0, config.train_frames) if k < config.train_frames else (config.train_frames, config.frames)
            views = renderer.render_frame(k, offsets=offsets, segment=segment)
            for c, (img, cov) in enumerate(views):
                u8 = _to_u8(sensor_image(img, gains[c], config.noise_std, noise_rng(config.seed, c, k)))
                write_image(tmp / "images" / names[c] / f"{k:06d}.jpg", u8[..., ::-1], jpeg)
                write_image(masks_dir / names[c] / f"{k:06d}.png", np.where(cov >= 0.5, 255, 0).astype(np.uint8))
                if k in sheet_frames:
                    sheet_tiles[(k, c)] = u8
                if video is not None and c == 0:
                    video.send(u8)
            if progress:
                progress(ProgressReport(done=k + 1, total=len(frames), part="render"))
        if video is not None:
            video.close()
        stats["render_s"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        bm = BodyMotion(body_model="anny", frame_index=np.array(frames), fps=motion.fps,
                        pose_parameters=motion.pose_parameters[motion.written_rows], phenotype=motion.phenotype,
                        phenotype_labels=PHENOTYPE_LABELS)
        from avatarctl.body.anny_model import AnnyBody

        bone_labels = np.array(AnnyBody("cpu").joint_names)
        (tmp / GT_GEOMETRY).parent.mkdir(exist_ok=True)
        written = bm
        if config.fit_noise_deg or config.fit_noise_cm:  # realistic fit errors; the truth goes to gt/
            from avatarctl.body.perturb import perturb_motion

            written = perturb_motion(bm, config.fit_noise_deg, config.fit_noise_cm, seed=config.seed,
                                     corr_frames=config.fit_noise_corr_frames)
        if written is not bm or config.fits == "none":
            with open(tmp / GT_MOTION, "wb") as fh:
                np.savez(fh, **bm.to_npz_dict(), bone_labels=bone_labels)
        if config.fits == "truth":  # "none": ingest estimates them (--fits keypoints)
            with open(tmp / "motion.npz", "wb") as fh:
                np.savez(fh, **written.to_npz_dict(), bone_labels=bone_labels)
        with open(tmp / GT_GEOMETRY, "wb") as fh:
            np.savez(fh, frame_index=np.array(frames), body_vertices=scene.body_vertices,
                     garment_vertices=scene.skirt_vertices, body_faces=scene.body_faces,
                     garment_faces=scene.skirt_faces, garment_param=scene.skirt_param.astype(np.float32),
                     garment_hem=scene.skirt_hem, body_rest_vertices=scene.body_rest,
                     body_region=scene.body_region.astype(np.int8), hem_radius=hem_radius.astype(np.float32))
        split = {"train_frames": train_frames, "test_frames": test_frames, "train_views": train_views,
                 "test_views": test_views}
        (tmp / "split.json").write_text(json.dumps(split, indent=2) + "\n")
        contact_sheet(tmp / "contact_sheet.png", sheet_tiles, sheet_frames, names, hem_radius, config)
        stats["write_s"] = time.perf_counter() - t0
        stats["total_s"] = time.perf_counter() - t_all
        timings = {k: round(float(v), 3) for k, v in stats.items() if k.endswith("_s") or k.endswith("_frame")}
        info = {
            "generator": GENERATOR_VERSION,
            "preset": config.preset,
            "seed": config.seed,
            "config": config.to_json(),
            "frames": {"train": len(train_frames), "test": len(test_frames), "fps": motion.fps,
                       "sim_fps": config.sim_fps, "warmup_frames": config.warmup_frames},
            "body": {"model": "anny", "phenotype": dict(zip(PHENOTYPE_LABELS, map(float, motion.phenotype)))},
            "garment": {"type": config.garment, "particles": int(scene.skirt_vertices.shape[1]),
                        "max_penetrating_particles": int(stats["max_penetrating_particles"]),
                        "hem_radius_m": {"min": float(hem_radius.min()), "max": float(hem_radius.max())}},
            "hem_pair": hem_pair,
            "floor_z": scene.floor_z,
            "mask_rule": f"subpixel coverage >= 0.5 with {config.supersample}x{config.supersample} rays per pixel",
            "imperfections": config.imperfections,
            "camera_colour": {n: [round(float(g), 6) for g in gains[c]] for c, n in enumerate(names)},
            "clean_twin": config.clean_twin().to_json(),
            "timings": timings,
        }
        (tmp / "capture.json").write_text(json.dumps(info, indent=2) + "\n")
    return SynthResult(out=out, cameras=cameras, train_frames=train_frames, test_frames=test_frames,
                       train_views=train_views, test_views=test_views, timings=timings, hem_pair=hem_pair,
                       max_penetrating_particles=int(stats["max_penetrating_particles"]),
                       hem_radius_range=(float(hem_radius.min()), float(hem_radius.max())))


class _VideoWriter:
    """The `layout = "video"` file: H.264 frames of one camera, its 35 mm-equivalent focal length in the metadata
    (`FOCAL_35MM_TAG`; 35 mm-equivalent focal = focal_px x 43.27 mm / image diagonal in px)."""

    def __init__(self, path: Path, cam: Camera, fps: float):
        import imageio_ffmpeg

        f35 = float(cam.K[0, 0]) * FULL_FRAME_DIAGONAL_MM / float(np.hypot(cam.width, cam.height))
        self._gen = imageio_ffmpeg.write_frames(
            str(path), (cam.width, cam.height), fps=fps, quality=9, macro_block_size=1,
            output_params=["-metadata", f"{FOCAL_35MM_TAG}={f35:.2f}", "-movflags", "use_metadata_tags"])
        self._gen.send(None)

    def send(self, rgb: np.ndarray) -> None:
        """One RGB uint8 [H, W, 3] frame."""
        self._gen.send(np.ascontiguousarray(rgb))

    def close(self) -> None:
        self._gen.close()


def _sheet_frames(config: SynthConfig, hem_radius: np.ndarray, hem_pair: dict | None) -> list[int]:
    """Frames shown on the contact sheet: first, widest hem, the hem pair (if any), a test frame."""
    n_tr = config.train_frames
    picks = [0, int(hem_radius[:n_tr].argmax())]
    if hem_pair:
        picks += hem_pair["frames"]
    picks += [n_tr + int(hem_radius[n_tr:].argmax()), config.frames - 1]
    seen: list[int] = []
    for p in picks:
        if p not in seen:
            seen.append(p)
    return seen[:6]
