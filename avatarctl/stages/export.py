"""The export stage (`avatarctl export PROJECT`): a fitted avatar -> posed meshes and an animatable skinned glTF.

Steps:
1. load the fitted avatar (`stages.common.load_fitted`); choose the motion: the project's own frames (training frames
   with the cVAE latent z = mu, novel ones with z = 0, as `render`) or a motion file (`--poses`, z = 0; any rig
   `render --poses` takes, retargeted onto the avatar's body model when made for another: `motion_for_avatar`);
2. the surface level (`--threshold auto`, the default; `export.level`): on one training frame (the first posed
   frame that is one, else the project's first training frame), candidate levels around the body level b (the
   density just inside the body model's skin, `export.mesh.body_level`) are meshed and rendered in a few TRAINING
   views and the one with the best PSNR against the photographs wins; every mesh of the export (each posed frame,
   the rest pose) then takes its own body level times the chosen factor (level / b). A number (`--threshold 10`)
   is used as it is for every mesh;
3. posed meshes (`--frames`, default the first training frame / the motion file's first frame): the density field
   of the frame sampled on a grid over the node supports, marching cubes at the level, vertex colours baked by
   rendering each vertex head-on along its normal (`export.mesh`; a Gaussian field's from its rasterized images
   around the mesh, `export.view_colours`); written as GLB / PLY / OBJ (the scoring frame's
   mesh is the chosen candidate of step 2, finished);
4. the animatable avatar `avatar.glb`: one mesh extracted the same way in the canonical (rest) pose
   (`export.mesh.rest_node_state`: M_j = identity, z = 0), skinning weights transferred from the body template
   (inverse-distance blend of the 4 nearest template vertices, the 4 (or `influences` = 8) largest kept), the body
   model's joints as a glTF node tree bound at their centres (`body.joints.joint_centres` over the project's
   poses), and the motion (the project's frames, or `--poses`) as a glTF animation (`export.skinning`,
   `export.gltf`);
5. the reload check: `avatar.glb` is read back with pygltflib and skinned from the file's own data
   (`export.gltf_read`), against our LBS (`body.lbs.lbs`) on sampled animation frames: the vertex error with the
   exported 4 weights (file fidelity) and with the dense transferred weights (what truncation to 4 costs);
6. with `--score`: every posed project frame rendered as a mesh (`export.raster`, unlit baked colours) and as the
   volume (`render.engine.render_view`) in the held-out views, both scored against the same ground truth under the
   eval `bbox` protocol with the one metrics module (`evaluate.metrics`);
7. `export.json` (config, the level candidates and their scores, sizes, pieces, timings, reload errors, scores) and
   `preview.png` (ground truth | volume | mesh of
   the first posed frame in the first held-out view) are written with the meshes into a temporary directory,
   renamed into place (`atomic_dir`), and the stage is recorded.

Frames of the files: PLY / OBJ in the capture's world frame (metres, the cameras' frame). GLB files (posed meshes and
avatar.glb alike) in one frame that other tools expect (`export.skinning.glb_frame`): rotated so the capture's up
(estimated from the cameras) is glTF's +Y, and moved so the origin is on the ground under the body: height 0 is the
lowest point the body template's feet reach over the motion (the project's frames, or `--poses`), the horizontal
origin the middle of the body's footprint in the motion's first frame; the root motion is relative to it
(`export.json` "glb_frame": the 4x4 world -> file matrix, "glb_basis" its rotation).
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterator

import numpy as np

from avatarctl.errors import InputError
from avatarctl.frames import select_frames
from avatarctl.project import Project, check_name, now_iso
from avatarctl.progress import ProgressReport, ProgressFn
from avatarctl.stages.common import check_latent_mode, fitted_held_out_poses, frame_node_state, latent_for, \
    load_fitted, motion_for_avatar, open_fitted, writing

if TYPE_CHECKING:
    from avatarctl.export.level import LevelChoice

SCHEMA_VERSION = 3  # 2: threshold None = from the field; glb_frame; reload default_pose_max_m. 3: level_choice, pieces
MESH_FORMATS = ("glb", "ply", "obj")
SPLAT_FORMATS = ("splat", "player")  # Gaussian-field avatars: per-frame 3DGS .ply, the HTML player (_splats)
FORMATS = MESH_FORMATS + SPLAT_FORMATS
PLAYER_FRAMES = 30  # frames of the player without --frames
CHECK_FRAMES = 8  # animation frames of the reload check


@dataclass(frozen=True)
class ExportConfig:
    """What `avatarctl export` writes. Saved in `export/<name>/export.json` and the manifest."""

    name: str = "default"  # output folder export/<name>
    frames: str | None = None  # posed meshes (see avatarctl.frames); None = the first training / motion frame
    posed: bool = True  # write posed meshes
    skinned: bool = True  # write the animatable avatar.glb
    poses: str | None = None  # motion file: the posed frames and the animation; None = the project's frames
    formats: tuple[str, ...] = ("glb", "ply")  # posed mesh files: glb | ply | obj; Gaussian fields: splat | player
    voxel: float = 0.008  # grid spacing, metres
    threshold: float | None = None  # density level of the surface, 1/metre; None = chosen by the training views
    #                                 (export.level: the body level times the best-scoring factor)
    min_component: float = 0.01  # drop connected pieces with fewer than this fraction of the faces
    influences: int = 4  # skinning weights per vertex in avatar.glb: 4 (JOINTS_0) or 8 (+ JOINTS_1)
    latent: str = "auto"  # auto | mean | zero | sample (posed meshes; the rest mesh uses z = 0)
    seed: int = 0
    recenter: bool = True  # --poses: move the motion to where the avatar's first training frame stands
    score: bool = False  # mesh vs volume PSNR of the posed project frames in the held-out views
    device: str = "auto"
    checkpoint: str | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "formats", tuple(dict.fromkeys(f.strip().lower().lstrip(".") for f in self.formats)))
        check_name(self.name, "export name")
        check_latent_mode(self.latent)
        bad = [f for f in self.formats if f not in FORMATS]
        if bad or not self.formats:
            raise InputError(f"unknown mesh format(s) {bad or '(none)'}", where="--format",
                             fix=f"use a comma list of {', '.join(FORMATS)}")
        if not 0.001 <= self.voxel <= 0.1:
            raise InputError(f"--voxel {self.voxel} m outside [0.001, 0.1]", where="--voxel", fix="e.g. --voxel 0.008")
        if self.threshold is not None and not self.threshold > 0:
            raise InputError(f"--threshold must be > 0 (1/metre), got {self.threshold}", where="--threshold",
                             fix="e.g. --threshold 10")
        if not 0.0 <= self.min_component < 1.0:
            raise InputError(f"min component fraction {self.min_component} outside [0, 1)", fix="e.g. 0.01")
        if self.influences not in (4, 8):
            raise InputError(f"--influences {self.influences}: glTF sets hold 4 weights", where="--influences",
                             fix="use 4 (every viewer) or 8 (two sets; Blender, not three.js)")
        if not (self.posed or self.skinned):
            raise InputError("nothing to export (--no-posed and --no-skinned)", fix="drop one of them")
        if self.score and (self.poses or not self.posed):
            raise InputError("--score needs posed meshes of the project's frames", where="--score",
                             fix="drop --poses / --no-posed, or drop --score")

    def to_json(self) -> dict[str, Any]:
        d = asdict(self)
        d["formats"] = list(self.formats)
        return {"schema_version": SCHEMA_VERSION, **d}


@dataclass(frozen=True)
class ExportedMesh:
    frame: int
    latent: str
    files: dict[str, int]  # relative file -> bytes
    vertices: int
    faces: int
    threshold: float  # the surface level used, 1/metre
    grid_points: int  # density evaluations (grid points inside a node support)
    pieces: int  # connected pieces of the mesh
    largest_piece: float  # the largest piece's share of the faces
    seconds: float  # the scoring frame's includes the level search


@dataclass(frozen=True)
class MeshScore:
    """One (frame, view): the mesh and the volume render scored against the same ground truth (eval bbox)."""

    frame: int
    view: str
    split: str  # novel_view (training frame) | novel_pose
    psnr_mesh: float
    psnr_volume: float
    mesh_seconds: float
    volume_seconds: float


@dataclass(frozen=True)
class SkinnedExport:
    file: str
    bytes: int
    vertices: int
    faces: int
    threshold: float  # the surface level of the rest mesh, 1/metre
    pieces: int  # connected pieces of the rest mesh
    largest_piece: float  # the largest piece's share of the faces
    joints: int
    animation_frames: int
    animation_source: str
    seconds: float
    trs_residual: float  # max |TRS - local joint matrix| (0 for rigid joint transforms)
    weight_mass_dropped: float  # max weight mass lost by keeping `influences` weights per vertex
    reload: dict[str, Any]  # the reload check (step 4): errors in metres, or the reason it was skipped


@dataclass(frozen=True)
class ChosenLevel:
    """`--threshold auto`: the level chosen on one training frame (`export.level`); every mesh of the export takes its
    own body level times `choice.factor`."""

    frame: int
    choice: "LevelChoice"


@dataclass
class ExportResult:
    out_dir: Path
    meshes: list[ExportedMesh]
    avatar: SkinnedExport | None
    scores: list[MeshScore]
    seconds: float
    checkpoint_step: int
    splats: dict[str, int] = field(default_factory=dict)  # splat / player files -> bytes
    level: ChosenLevel | None = None  # --threshold auto: the candidates and their training-view scores

    def mean_psnr(self) -> tuple[float, float] | None:
        if not self.scores:
            return None
        return (float(np.mean([s.psnr_mesh for s in self.scores])),
                float(np.mean([s.psnr_volume for s in self.scores])))


def run(project_dir: str | Path, cfg: ExportConfig, progress: ProgressFn | None = None, *,
        wait: bool = False) -> ExportResult:
    """Run the export stage on `project_dir` (see the module docstring). Holds the lock of `export/<name>`; `wait`:
    for another command writing it to finish, instead of refusing (`BusyError`)."""
    out_dir = Project.open(project_dir).paths.export(cfg.name)
    with writing(out_dir, f"export --name {cfg.name}", wait, sweep=True):
        return _run(project_dir, cfg, progress)


def _run(project_dir: str | Path, cfg: ExportConfig, progress: ProgressFn | None) -> ExportResult:
    from avatarctl.atomic import atomic_dir, write_json
    from avatarctl.render.trajectories import up_from_cameras

    from avatarctl.export.mesh import mesh_pieces
    from avatarctl.export.skinning import glb_frame, up_to_y_basis

    started = now_iso()
    t_start = time.perf_counter()
    project = open_fitted(project_dir, cfg.checkpoint, (), cfg.poses)
    if "ply" in cfg.formats or "obj" in cfg.formats:
        _require("trimesh", "writing .ply / .obj", "or use --format glb")
    avatar = load_fitted(project, cfg.device, cfg.checkpoint)
    held = fitted_held_out_poses(avatar) if cfg.poses is None else None  # the project's held-out frames: the fit's
    cap = avatar.capture
    basis = up_to_y_basis(up_from_cameras(list(cap.cameras.values())))
    train_set = set(int(f) for f in avatar.train_frames)
    retarget: str | None = None
    if cfg.poses is None:
        motion, source = cap.motion, "project"
        pool = cap.frames
        default = [min(train_set)] if train_set else pool[:1]
    else:
        (motion, retarget), source = motion_for_avatar(avatar, cfg.poses, cfg.recenter), str(cfg.poses)
        pool = [int(f) for f in motion.frame_index]
        default = pool[:1]
    mesh_formats = tuple(f for f in cfg.formats if f in MESH_FORMATS)
    splat_formats = tuple(f for f in cfg.formats if f in SPLAT_FORMATS)
    if splat_formats and not avatar.model.field_kind.splats:
        raise InputError(f"--format {','.join(splat_formats)} needs a Gaussian-field avatar", where="--format",
                         fix="fit with the cpu preset (the Gaussian fields), or export glb / ply / obj")
    if "player" in splat_formats and cfg.frames is None:
        default = pool[:PLAYER_FRAMES]
    frame_glb = glb_frame(basis, _ground_origin(avatar, motion, basis))
    frames = (select_frames(cfg.frames, pool, train=cap.split.train_frames if cfg.poses is None else None,
                            test=cap.split.test_frames if cfg.poses is None else None)
              if cfg.frames is not None else default) if cfg.posed else []
    splat_columns: list[dict[str, np.ndarray]] = []
    splat_files: dict[str, int] = {}
    total = len(frames) + int(cfg.skinned)
    out_dir = project.paths.export(cfg.name)
    meshes: list[ExportedMesh] = []
    scores: list[MeshScore] = []
    skinned: SkinnedExport | None = None
    preview: list[np.ndarray] = []
    t0 = time.perf_counter()

    def report(part: str) -> None:
        if progress is not None:
            progress(ProgressReport(stage="export", done=len(meshes) + int(skinned is not None), total=total,
                                    seconds=time.perf_counter() - t0, part=part))

    with atomic_dir(out_dir) as tmp:
        chosen: ChosenLevel | None = None
        first: Any = None  # the scoring frame's mesh when it is one of `frames` (step 3)
        factor, first_seconds = 1.0, 0.0
        if cfg.threshold is None and mesh_formats and (frames or cfg.skinned):
            report("choosing the surface level")
            ts = time.perf_counter()
            chosen, first = _choose_level(avatar, cfg, frames if cfg.poses is None else [], train_set)
            factor, first_seconds = chosen.choice.factor, time.perf_counter() - ts
        for frame in frames:
            is_train = cfg.poses is None and frame in train_set
            latent = latent_for(cfg.latent, is_train)
            one = motion.for_frames([frame])
            state = frame_node_state(avatar, one, frame, is_train, latent, cfg.seed, held)
            if splat_formats:
                splat_columns.append(_splats(tmp, frame, avatar, state, "splat" in splat_formats, splat_files))
            if not mesh_formats:
                report("posed")
                continue
            ts = time.perf_counter()
            body = avatar.body.pose(one).vertices[0].detach().float().cpu().numpy()
            if first is not None and chosen is not None and frame == chosen.frame:  # step 2 meshed it
                (mesh, queried), level, spent = first, chosen.choice.level, first_seconds
            else:
                (mesh, queried, level), spent = _extract(avatar, state, cfg, f"frame {frame}", body, factor), 0.0
            files = _write_posed(tmp, frame, mesh, mesh_formats, frame_glb)
            pieces, largest = mesh_pieces(mesh.faces, mesh.num_vertices)
            meshes.append(ExportedMesh(frame=frame, latent=latent, files=files, vertices=mesh.num_vertices,
                                       faces=mesh.num_faces, threshold=round(level, 4), grid_points=queried,
                                       pieces=pieces, largest_piece=round(largest, 4),
                                       seconds=round(time.perf_counter() - ts + spent, 3)))
            if cfg.score:
                scores += _score(avatar, one, state, mesh, frame, is_train, preview if not preview else None)
            elif not preview:
                preview.append(_mesh_preview(avatar, mesh))
            report("posed")
        if "player" in splat_formats:
            from avatarctl.export.player import pack_frames, write_player
            from avatarctl.render.trajectories import up_from_cameras as _up

            fps = float(motion.fps) if motion.fps > 0 else 30.0
            block = pack_frames(splat_columns, fps, _up(list(cap.cameras.values())), [f"frame {f}" for f in frames],
                                avatar.model.cfg.gaussians.low_pass)
            write_player(tmp / "player.html", block, f"avatarctl player: {project.root.name}")
            splat_files["player.html"] = (tmp / "player.html").stat().st_size
        if cfg.skinned and mesh_formats:  # the skinned avatar is a mesh product: not with splat formats alone
            skinned = _export_skinned(tmp, avatar, cfg, motion, source, frame_glb, factor)
            report("skinned")
        if preview:
            from avatarctl.render.images import write_png

            write_png(tmp / "preview.png", np.concatenate(preview, axis=1), None)
        result = ExportResult(out_dir=out_dir, meshes=meshes, avatar=skinned, scores=scores,
                              seconds=round(time.perf_counter() - t_start, 3), checkpoint_step=avatar.step,
                              splats=splat_files, level=chosen)
        write_json(tmp / "export.json", _record(cfg, avatar, result, frame_glb, source, retarget))
    project.record("export", config=cfg.to_json(), outputs=[out_dir], started=started,
                   summary={"name": cfg.name, "meshes": len(meshes), "avatar": skinned.file if skinned else None,
                            "checkpoint_step": avatar.step, "motion": source,
                            **({"level_factor": chosen.choice.factor} if chosen else {}),
                            **({"psnr_mesh": round(result.mean_psnr()[0], 3),
                                "psnr_volume": round(result.mean_psnr()[1], 3)} if scores else {})})
    return result


def _splats(tmp: Path, frame: int, avatar: Any, state: Any, write: bool, files: dict[str, int]) -> dict[str, Any]:
    """The 3DGS .ply columns of one posed frame (`export.splat_ply`); written as splats/<frame:06d>.ply if `write`."""
    import torch

    from avatarctl.export.splat_ply import splat_arrays, write_splat_ply

    with torch.no_grad():
        posed = avatar.model.posed_gaussians(state)
        cols = splat_arrays(posed.means[0], posed.covars[0], posed.sh[0], posed.opacities[0],
                            state.transforms[0, :, :3, :3], posed.per_node)
    if write:
        rel = f"splats/{frame:06d}.ply"
        (tmp / "splats").mkdir(exist_ok=True)
        write_splat_ply(tmp / rel, cols, avatar.model.cfg.gaussians.low_pass)
        files[rel] = (tmp / rel).stat().st_size
    return cols


def _require(module: str, what: str, alternative: str = "") -> None:
    import importlib.util

    if importlib.util.find_spec(module) is None:
        raise InputError(f"{what} needs the `{module}` package", where="avatarctl[export]",
                         fix=f"pip install 'avatarctl[export]' {alternative}".strip())


def _field(avatar: Any, state: Any, voxel: float) -> tuple[Any, Any]:
    """(density, vertex colouring) of frame slot 0 of `state` (`export.mesh` callables). The density of every field
    at points (the Gaussian field's is `splat.density`'s binned kernel); the colours of a ray-marched field's mesh
    baked head-on (`mesh.head_on_bake`, rays from 2 voxels outside), a Gaussian field's from its rasterized images
    around the mesh (`export.view_colours`: 21.14 dB against the bake's 20.18 on the demo capture, docs/export_view.md)."""
    from avatarctl.export.mesh import head_on_bake, slrf_density, slrf_ray_colour
    from avatarctl.render.trajectories import up_from_cameras

    model = avatar.model
    if not model.field_kind.splats:
        background = tuple(float(c) for c in avatar.background)
        return slrf_density(model, state), head_on_bake(slrf_ray_colour(model, state), 2.0 * voxel, background)
    from avatarctl.export.view_colours import gaussian_views, view_colouring

    up = up_from_cameras(list(avatar.capture.cameras.values()))
    return slrf_density(model, state), view_colouring(gaussian_views(model, state), up)


@contextmanager
def _surface_errors(what: str) -> Iterator[None]:
    """The meshing errors of `export.mesh` / `export.level` as one-line input errors."""
    from avatarctl.export.mesh import GridTooLargeError, NoSurfaceError

    try:
        yield
    except NoSurfaceError as e:
        raise InputError(f"no surface to mesh for {what}: {e}", where="--threshold",
                         fix="lower --threshold (or fit longer)") from None
    except GridTooLargeError as e:
        raise InputError(str(e), where="--voxel", fix="use a larger --voxel") from None


def _extract(avatar: Any, state: Any, cfg: ExportConfig, what: str, body: np.ndarray,
             factor: float) -> tuple[Any, int, float]:
    """The coloured mesh of frame slot 0 of `state` (export.mesh) -> (mesh, grid points queried, the level used);
    body [V, 3]: the body model posed like `state` (the level's probes when `cfg.threshold` is None: its body level
    times `factor`, step 2). A one-line error when there is no surface."""
    from avatarctl.export.mesh import body_level, extract_mesh

    model = avatar.model
    density, colour = _field(avatar, state, cfg.voxel)
    with _surface_errors(what):
        level = cfg.threshold if cfg.threshold is not None else factor * body_level(
            density, body, avatar.template.faces.cpu().numpy())
        mesh, queried = extract_mesh(density, colour, state.centers[0].detach().float().cpu().numpy(),
                                     float(model.cfg.support_radius), cfg.voxel, level, cfg.min_component)
    return mesh, queried, level


def _choose_level(avatar: Any, cfg: ExportConfig, frames: list[int], train_set: set[int]
                  ) -> tuple[ChosenLevel, tuple[Any, int] | None]:
    """Step 2 on the first of `frames` that is a training frame, else the project's first training frame ->
    (the choice, (the mesh at the chosen level, grid points queried) when the scoring frame is one of `frames`)."""
    from avatarctl.export.level import choose_level, pick_views, scoring_image
    from avatarctl.export.mesh import body_level, density_grid

    cap = avatar.capture
    if not train_set:
        raise InputError("--threshold auto scores the surface levels on training frames; the fit has none",
                         where="--threshold", fix="give a level, e.g. --threshold 10")
    frame = next((f for f in frames if f in train_set), min(train_set))
    one = cap.motion.for_frames([frame])
    state = frame_node_state(avatar, one, frame, True, latent_for(cfg.latent, True), cfg.seed)
    body = avatar.body.pose(one).vertices[0].detach().float().cpu().numpy()
    background = tuple(float(c) for c in avatar.background)
    images = [scoring_image(v, cap.cameras[v], cap.image(v, frame), cap.mask(v, frame), background, body)
              for v in pick_views(list(cap.split.train_views) or sorted(cap.cameras))]
    model = avatar.model
    density, colour = _field(avatar, state, cfg.voxel)
    with _surface_errors(f"frame {frame}"):
        base = body_level(density, body, avatar.template.faces.cpu().numpy())
        grid = density_grid(density, state.centers[0].detach().float().cpu().numpy(),
                            float(model.cfg.support_radius), cfg.voxel, level=base)
        choice, mesh = choose_level(grid, base, colour, images, background, cfg.min_component)
    return ChosenLevel(frame=frame, choice=choice), ((mesh, grid.queried) if frame in frames else None)


def _ground_origin(avatar: Any, motion: Any, basis: np.ndarray, chunk: int = 64) -> np.ndarray:
    """[3] world point that becomes the GLB files' origin (module docstring): the body template posed over `motion`,
    its lowest point along the up axis over all frames, the middle of its first frame's footprint."""
    from avatarctl.export.skinning import ground_origin

    up = np.asarray(basis, np.float64)[1]
    lowest, first = np.inf, None
    for s in range(0, motion.num_frames, chunk):
        v = avatar.body.pose(motion.select(slice(s, s + chunk))).vertices.detach().double().cpu().numpy()
        first = v[0] if first is None else first
        lowest = min(lowest, float((v @ up).min()))
    return ground_origin(first, lowest, basis)


def _in_frame(mesh: Any, frame: np.ndarray) -> Any:
    """The mesh in the GLB files' frame (a [4, 4] `export.skinning.glb_frame`)."""
    from dataclasses import replace

    from avatarctl.export.skinning import to_frame

    return replace(mesh, vertices=to_frame(mesh.vertices, frame).astype(np.float32),
                   normals=(mesh.normals @ frame[:3, :3].T.astype(np.float32)).astype(np.float32))


def _write_posed(tmp: Path, frame: int, mesh: Any, formats: tuple[str, ...], glb: np.ndarray) -> dict[str, int]:
    from avatarctl.export.gltf import write_mesh

    (tmp / "meshes").mkdir(exist_ok=True)
    files = {}
    for fmt in formats:
        rel = f"meshes/{frame:06d}.{fmt}"
        write_mesh(tmp / rel, _in_frame(mesh, glb) if fmt == "glb" else mesh)
        files[rel] = (tmp / rel).stat().st_size
    return files


def _mesh_preview(avatar: Any, mesh: Any) -> np.ndarray:
    from avatarctl.export.raster import render_mesh

    cap = avatar.capture
    view = (cap.split.test_views or cap.split.train_views or list(cap.cameras))[0]
    return render_mesh(mesh, cap.cameras[view].pinhole(), avatar.background).rgb


def _score(avatar: Any, one: Any, state: Any, mesh: Any, frame: int, is_train: bool,
           preview: list[np.ndarray] | None) -> list[MeshScore]:
    """Step 5 for one frame over the held-out views; fills `preview` (gt | volume | mesh) from the first view."""
    from avatarctl.evaluate.metrics import psnr
    from avatarctl.evaluate.protocols import bbox_region, ground_truth
    from avatarctl.export.raster import render_mesh
    from avatarctl.render.engine import render_view

    cap = avatar.capture
    verts = avatar.body.pose(one).vertices[0].detach().float().cpu().numpy()
    out = []
    for view in cap.split.test_views:
        cam = cap.cameras[view].pinhole()
        region = bbox_region(cam, verts)
        gt = ground_truth(cap.image(view, frame), cap.mask(view, frame), avatar.background)
        ts = time.perf_counter()
        mesh_img = render_mesh(mesh, cam, avatar.background).rgb
        mesh_s = time.perf_counter() - ts
        x0, y0, x1, y1 = region.crop
        box = np.zeros((cam.height, cam.width), bool)
        box[y0:y1, x0:x1] = True
        vol = render_view(avatar.model, state, 0, cam, avatar.background, pixel_mask=box)
        out.append(MeshScore(frame=frame, view=view, split="novel_view" if is_train else "novel_pose",
                             psnr_mesh=round(psnr(mesh_img, gt, region.mask), 4),
                             psnr_volume=round(psnr(vol.rgb, gt, region.mask), 4),
                             mesh_seconds=round(mesh_s, 4), volume_seconds=round(vol.seconds, 4)))
        if preview is not None and not preview:
            preview += [region.crop_image(gt), region.crop_image(vol.rgb), region.crop_image(mesh_img)]
    return out


def _export_skinned(tmp: Path, avatar: Any, cfg: ExportConfig, motion: Any, source: str,
                    frame: np.ndarray, factor: float) -> SkinnedExport:
    """Steps 4 and 5: avatar.glb and its reload check; `factor`: the level factor of step 2."""
    import torch

    from avatarctl.body.joints import joint_centres, skin_weighted_centroids
    from avatarctl.export import skinning
    from avatarctl.export.gltf import Animation, SkinnedMesh, glb_bytes
    from avatarctl.export.mesh import mesh_pieces, rest_node_state

    ts = time.perf_counter()
    tpl = avatar.template
    mesh, _, level = _extract(avatar, rest_node_state(avatar.model), cfg, "the rest pose",
                              tpl.vertices.cpu().numpy(), factor)
    pieces, largest = mesh_pieces(mesh.faces, mesh.num_vertices)
    dense = skinning.transfer_weights(mesh.vertices, tpl.vertices.cpu().numpy(), tpl.skin_weights.cpu().numpy())
    weights = skinning.sparsify(dense, cfg.influences)
    cap = avatar.capture
    M_capture = _joint_transforms(avatar, cap.motion)  # [frames, J, 4, 4] the project's poses: pivots
    M = M_capture if motion is cap.motion else _joint_transforms(avatar, motion)
    fallback = skin_weighted_centroids(tpl.vertices.cpu(), tpl.skin_weights.cpu())
    pivots = joint_centres(torch.from_numpy(M_capture), tpl.parents, fallback).numpy()  # [J, 3] canonical
    pivots_y = skinning.to_frame(pivots, frame)
    M_y = skinning.conjugate(M, frame)
    ibm = np.tile(np.eye(4), (len(tpl.parents), 1, 1))
    ibm[:, :3, 3] = -pivots_y
    trs = skinning.local_trs(skinning.joint_globals(M_y, pivots_y), tpl.parents)
    fps = float(motion.fps) if motion.fps > 0 else 30.0
    times = (np.asarray(motion.frame_index, np.float64) - float(motion.frame_index[0])) / fps
    if len(times) > 1 and not np.all(np.diff(times) > 0):
        times = np.arange(len(times)) / fps
    mesh_y = _in_frame(mesh, frame)
    first = skinning.JointTrs(translation=trs.translation[:1], rotation=trs.rotation[:1], scale=trs.scale[:1],
                              residual=trs.residual)  # the joints' own TRS: the first frame, standing on the floor
    skin = SkinnedMesh(weights=weights, joint_names=tpl.joint_names, parents=tpl.parents, pose=first, inverse_bind=ibm)
    data = glb_bytes(mesh_y, skin, (Animation(name=Path(source).stem if source != "project" else "capture",
                                              times=times, trs=trs),))
    (tmp / "avatar.glb").write_bytes(data)
    seconds = time.perf_counter() - ts
    reload = _reload_check(tmp / "avatar.glb", mesh_y, weights, dense, M_y)
    return SkinnedExport(file="avatar.glb", bytes=len(data), vertices=mesh.num_vertices, faces=mesh.num_faces,
                         threshold=round(level, 4), pieces=pieces, largest_piece=round(largest, 4),
                         joints=len(tpl.parents), animation_frames=len(times), animation_source=source,
                         seconds=round(seconds, 3), trs_residual=float(trs.residual),
                         weight_mass_dropped=round(weights.dense_residual, 6), reload=reload)


def _joint_transforms(avatar: Any, motion: Any, chunk: int = 64) -> np.ndarray:
    """[frames, J, 4, 4] M_j(theta) of every row of `motion` (float64, world)."""
    out = [avatar.body.pose(motion.select(slice(s, s + chunk))).joint_transforms.detach().double().cpu().numpy()
           for s in range(0, motion.num_frames, chunk)]
    return np.concatenate(out)


def _reload_check(path: Path, mesh_y: Any, weights: Any, dense: np.ndarray, M_y: np.ndarray) -> dict[str, Any]:
    """Step 5: max / mean vertex error (metres) of the file skinned by its own data vs our LBS."""
    import importlib.util

    if importlib.util.find_spec("pygltflib") is None:
        return {"checked": False, "reason": "pygltflib not installed (pip install 'avatarctl[export]')"}
    import torch

    from avatarctl.body.lbs import lbs
    from avatarctl.export.gltf_read import pose_glb, read_skinned_glb

    data = read_skinned_glb(path)
    F = M_y.shape[0]
    sel = sorted(set(np.linspace(0, F - 1, min(CHECK_FRAMES, F)).round().astype(int).tolist()))
    v = torch.from_numpy(mesh_y.vertices.astype(np.float64))
    w4 = torch.from_numpy(weights.dense(dense.shape[1]).astype(np.float64))
    wd = torch.from_numpy(dense.astype(np.float64))
    Ms = torch.from_numpy(M_y[sel])
    ours4, ours_dense = lbs(v, w4, Ms).numpy(), lbs(v, wd, Ms).numpy()  # [checked, verts, 3]
    theirs = np.stack([pose_glb(data, 0, f) for f in sel])
    default_err = float(np.abs(pose_glb(data) - ours4[0]).max()) if len(mesh_y.vertices) else 0.0  # sel[0] = 0
    e4 = np.linalg.norm(theirs - ours4, axis=-1)
    ed = np.linalg.norm(theirs - ours_dense, axis=-1)
    return {"checked": True, "reader": "pygltflib + export.gltf_read (the glTF skinning equation on the file's data)",
            "frames_checked": [int(f) for f in sel], "default_pose_max_m": default_err,
            "vs_lbs_same_weights_max_m": float(e4.max()), "vs_lbs_same_weights_mean_m": float(e4.mean()),
            "vs_lbs_dense_weights_max_m": float(ed.max()), "vs_lbs_dense_weights_mean_m": float(ed.mean())}


def _colour_rule(avatar: Any) -> str:
    """export.json's words for how the meshes' vertex colours were made (`_field`)."""
    if not avatar.model.field_kind.splats:
        from avatarctl.export.mesh import BAKE_RULE

        return BAKE_RULE
    from avatarctl.export.view_colours import VIEW_RULE

    return VIEW_RULE


def _record(cfg: ExportConfig, avatar: Any, res: ExportResult, frame: np.ndarray, source: str,
            retarget: str | None) -> dict[str, Any]:
    import torch

    mean = res.mean_psnr()
    return {"config": cfg.to_json(), "checkpoint": str(avatar.checkpoint) if avatar.checkpoint else None,
            "checkpoint_step": avatar.step, "motion_source": source, "retarget": retarget,
            "surface": {"threshold_per_m": cfg.threshold if cfg.threshold is not None else
                        "auto: the body level (the 25 % quantile of the density 1 cm inside the body model's skin, at "
                        "most 10) times the factor whose mesh scored best in training views (level_choice); per mesh: "
                        "meshes[].threshold, avatar.threshold",
                        "voxel_m": cfg.voxel, "min_component": cfg.min_component,
                        "colour": _colour_rule(avatar)},
            "glb_frame": frame.tolist(), "glb_basis": frame[:3, :3].tolist(),
            "glb_origin": "on the ground (the lowest point of the body template over the motion) under the middle "
                          "of the body's footprint in the motion's first frame; +Y up",
            "ply_obj_frame": "capture world (metres)",
            "level_choice": {"frame": res.level.frame, **asdict(res.level.choice),
                             "protocol": "PSNR (dB) of the mesh (unlit baked colours, 1 ray per pixel) vs the training "
                                         "photographs, bbox region, mean over the views"} if res.level else None,
            "meshes": [asdict(m) for m in res.meshes], "splats": res.splats,
            "avatar": asdict(res.avatar) if res.avatar else None,
            "scores": [asdict(s) for s in res.scores],
            "score_mean": {"psnr_mesh": mean[0], "psnr_volume": mean[1], "protocol": "bbox (eval), held-out views",
                           "mesh_render": "unlit baked vertex colours, 1 ray per pixel"} if mean else None,
            "timing": {"seconds": res.seconds, "device": str(avatar.device), "torch_threads": torch.get_num_threads()},
            "created": now_iso()}
