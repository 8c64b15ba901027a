"""Fit a body model (anny, SMPL, SMPL-X) to 3D body keypoints by gradient descent (the "own capture" path: no
body fits given).

The energy below is written once, in `fit_keypoints`; what differs between body models is a `KeypointBody`: its
keypoints K(θ, R, t, s) and vertices for per-frame rotation vectors θ, a root pose [R | t] and shape parameters
s shared over the frames, its shape prior P(s), a relative weight per keypoint, and the conversion of the fitted
parameters to a `BodyMotion`. `AnnyKeypoints` (below) is anny's; `avatarctl.body.smpl_keypoints.SmplKeypoints`
is SMPL's / SMPL-X's (body joints from the joint regressor, face and foot points picked from the template by
geometry); `keypoint_body` picks one for a loaded body model.

anny: the mesh ``V(θ, φ)`` for per-frame local-ref rotations θ (rotation vectors of `FIT_BONES`; every other
bone stays at anny's reference A-pose) and a root pose ``[R_f | t_f]`` (the root delta acts on the whole body in
world coordinates: ``V = R_f V_ref + t_f``), and one phenotype φ ∈ [0, 1]^6 per subject (sigmoid of free logits).
Keypoints are anny's `KeypointsRegressor.coco`, a fixed convex combination of vertices, ``K = W V`` (differentiable);
s = the phenotype's logits, P(s) = ‖φ − ½‖².

Energy minimised with Adam over all frames at once (in the spirit of SMPLify, Bogo et al. 2016, Eq. 1, with 3D
instead of 2D data):

    E = Σ_fj w_fj ρ(‖K_fj − X_fj‖) / Σ w          robust data term, ρ = Geman-McClure with scale σ (metres)
      + λ_pose   · mean_f Σ_b ‖θ_fb‖²             pose prior: stay near the reference pose
      + λ_smooth · mean_f Σ_b ‖θ_f+1,b − θ_fb‖²   temporal smoothness (and λ_trans for root translation)
      + λ_shape  · P(s)                           shape prior: stay near the average subject
      + λ_limit  · mean_f L(θ_f)                  joint limits of the hinge joints (0 where the body model has none)
      + λ_sil    · mean_fcv ρ_s(D_fc(π_c(v)) z_fcv / f_c)    silhouette term (optional, from step s_0 on)
      + λ_out    · mean_fco ρ_s(min_v ‖π_c(v) − o‖ z_v / f_c)  its other side: the masks' outline (optional, idem)

Monocular fits (one video, `ImageKeypointTargets`: 2D keypoints with confidences in one or more pinhole views)
replace the 3D data term with a reprojection term and add what one view cannot see:

    E_2D     = Σ_fcj w_fcj ρ(‖π_c(K_fj) − x_fcj‖ z_fcj / f_c) / Σ w    reprojection error in metres at the subject
      + λ_height · (h(s) − H)²                    the subject's standing height h(s) (reference pose, extent along
                                                  the body's up axis) near the given H: fixes the scale
      + λ_ground · mean_f∈G (min_j∈feet n·K_fj − d)²   ground contact: in the frames G where the feet are seen, the
                                                  lowest foot keypoint lies on one floor plane (n, d), fitted too
      + λ_root   · mean_f ‖R_f+1 − R_f‖²_F        root rotation smoothness (a turning subject)

The root starts from `initial_root_2d` (depth from the torso's size in the image, the heading chosen among 24
candidates by reprojection error and made temporally consistent by dynamic programming).

ρ(r) = σ² r² / (r² + σ²) (Geman & McClure 1987): quadratic for r ≪ σ, bounded for outliers. w_fj is the target's
weight times the body model's relative weight of keypoint j (SMPL's hips: `smpl_keypoints.HIP_WEIGHT`).

Silhouette term (one-sided): a subset of the posed vertices v is projected into every view c (π_c, pinhole, the
undistorted geometry); D_fc is the Euclidean distance transform of the *outside* of the person mask (OpenCV,
pixels to the nearest mask pixel, 0 inside), sampled bilinearly (`grid_sample`) so it is differentiable in the
vertex positions; times the vertex depth z over the focal length f it is a distance in metres at the subject, so the
weight does not depend on the resolution. It pushes the body *into* the masks and never pulls it out to fill them:
loose clothing makes a mask larger than the body. ρ_s is Geman-McClure with its own scale (a mask that misses a
hand must not drag the arm). It starts at step s_0 (a fraction of the steps), once the keypoints have placed the
body, and the share of projected vertices inside the masks (1 px tolerance) is reported at s_0 and at the end.
The outline term is the other side (a chamfer from the masks' outline to the projected body): up to
`OUTLINE_POINTS` points o spread along each view's mask outline (the boundary pixels of the distance field's inside)
pull the nearest projected vertex v of the same subset, the distance again in metres at that vertex's depth, ρ_s
again. It pulls a limb that the keypoints placed beside its silhouette back into it, which the one-sided term cannot
do when the limb lies over the torso's mask. Loose clothing makes it pull the body towards the cloth's outline, so
it joins at s_0 only when the outline lies within `OUTLINE_GATE_M` of the projected body on average (tight
clothes), and it is on for one video (`ingest.estimate.MONO_OUTLINE_WEIGHT`, where one view leaves the limbs'
placement to the image), off for triangulated keypoints. Reported: the outline's mean distance to the projected body
(metres at the subject) at s_0 and at the end, and whether the term ran.
Joint limits L(θ) (anny; none for SMPL yet): knees and elbows are hinges. With φ the rotation about the hinge's
flexion axis (knees: +x of the reference pose; elbows: the lowerarm bone's own x axis, `reference_bone_orientations`;
FACTS.md, checked: +φ bends), L = Σ_hinges relu(φ_lo − φ)² + relu(φ − φ_hi)², plus relu(|θ_⊥| − 10°)² for the knees'
rotation off that axis (a knee does not twist or bend sideways). Ranges (radians, from anny's reference pose: knees
straight, elbows pre-flexed 36.5°): knees [−5°, 150°], elbows [−40°, 115°]. Keypoints under a dress or a noisy
triangulation can otherwise bend a knee backwards.

Initialisation: θ = 0, s = 0 (anny φ = ½, SMPL β = 0), and the root by a weighted Kabsch / Umeyama (1991)
alignment of the rest pose's hips and shoulders (anny: reference A-pose, SMPL: T-pose) to the targets of each frame.

World frame of anny: +x subject's left, +y subject's back, +z up, metres. The capture's world frame may be any
orientation: the root rotation absorbs it.
"""

from __future__ import annotations

from dataclasses import dataclass
from dataclasses import replace
from typing import Protocol

import numpy as np
import torch

from avatarctl.body.motion import BodyMotion
from avatarctl.geometry.align import rigid_align
from avatarctl.progress import ProgressFn, ProgressReport

FIT_BONES = ("spine05", "spine04", "spine03", "spine02", "spine01", "neck01", "neck02", "neck03", "head",
             "clavicle.L", "clavicle.R", "upperarm01.L", "upperarm01.R", "lowerarm01.L", "lowerarm01.R",
             "upperleg01.L", "upperleg01.R", "lowerleg01.L", "lowerleg01.R", "foot.L", "foot.R")
TORSO = ("left_shoulder", "right_shoulder", "left_hip", "right_hip")
# hinge joints of anny's FIT_BONES: (bone, flexion axis: "x" = +x of the reference pose, "own" = the bone's own x axis,
# range of the flexion angle in degrees, limit on the rotation off that axis in degrees or None); module docstring
ANNY_HINGES = (("lowerleg01.L", "x", (-5.0, 150.0), 10.0), ("lowerleg01.R", "x", (-5.0, 150.0), 10.0),
               ("lowerarm01.L", "own", (-40.0, 115.0), None), ("lowerarm01.R", "own", (-40.0, 115.0), None))
SILHOUETTE_WEIGHT = 0.0  # the default λ_sil: off (measured: docs/experiments/silhouette_2026-11-25; 10 is the tried setting)
MAX_FIELD_SIDE = 128  # px: the larger side of the silhouette distance fields (64 KB per view at most)
OUTLINE_POINTS = 256  # mask outline points per view for the outline term (an even spread of the boundary pixels)
OUTLINE_WEIGHT = 0.0  # the default λ_out: off (triangulated keypoints; one video: ingest.estimate.MONO_OUTLINE_WEIGHT)
# the outline term's gate: at s_0 the masks' outline lies 1.2-1.3 cm from the keypoint-fitted body of a subject in
# tight clothes and 4.5 cm from one in a skirt, whose outline would pull the legs apart (synth phone, seeds 0 and 1,
# and with a skirt: docs/experiments/outline_term_2026-11-30/)
OUTLINE_GATE_M = 0.025


@dataclass(frozen=True)
class KeypointFitConfig:
    iters: int = 400  # Adam steps over all frames
    lr: float = 0.02  # Adam learning rate (rotation vectors in radians, translations in metres, logits)
    robust_scale_m: float = 0.10  # σ of the Geman-McClure data term
    w_pose: float = 1e-5  # λ_pose
    w_smooth: float = 1e-4  # λ_smooth (rotation vectors between consecutive fitted frames)
    w_trans: float = 1e-3  # λ_trans (root translation between consecutive fitted frames)
    w_shape: float = 1e-4  # λ_shape
    w_limits: float = 0.01  # λ_limit (0: off; measured: docs/experiments/silhouette_2026-11-25 "Joint limits")
    fit_shape: bool = True  # optimise the subject's shape (anny phenotype, SMPL betas); else the average subject
    w_silhouette: float = SILHOUETTE_WEIGHT  # λ_sil (0: off; used only when silhouettes are given)
    silhouette_scale_m: float = 0.05  # σ of the silhouette term's Geman-McClure (metres at the subject)
    silhouette_start: float = 0.5  # the silhouette term is on from this fraction of `iters` on
    silhouette_vertices: int = 2000  # posed vertices projected per frame (an even spread of anny's 13,718)
    w_outline: float = OUTLINE_WEIGHT  # λ_out: the masks' outline pulls the nearest projected vertex (0: off)
    outline_gate_m: float = OUTLINE_GATE_M  # the outline term joins at s_0 only if the outline is this close (mean)
    height_m: float | None = None  # H of the height prior (metres); None: no height prior
    w_height: float = 1.0  # λ_height (used only with `height_m`)
    w_ground: float = 0.0  # λ_ground (monocular fits; 0: off)
    w_root_smooth: float = 0.0  # λ_root (monocular fits; 0: off)

    def __post_init__(self) -> None:
        if self.iters < 0 or self.lr <= 0 or self.robust_scale_m <= 0 or not self.w_limits >= 0 \
                or not (self.w_height >= 0 and self.w_ground >= 0 and self.w_root_smooth >= 0) \
                or (self.height_m is not None and not 0.5 <= self.height_m <= 2.5):
            raise ValueError(f"bad keypoint-fit settings {self}")
        if not (self.w_silhouette >= 0 and self.w_outline >= 0 and self.outline_gate_m > 0
                and self.silhouette_scale_m > 0 and 0 <= self.silhouette_start < 1
                and self.silhouette_vertices > 0):
            raise ValueError(f"bad silhouette settings: weights {self.w_silhouette}, {self.w_outline} (>= 0), scale "
                             f"{self.silhouette_scale_m} (> 0), start {self.silhouette_start} (in [0, 1)), "
                             f"vertices {self.silhouette_vertices} (> 0)")


@dataclass(frozen=True)
class KeypointTargets:
    """3D keypoints to fit, one row per frame."""

    names: tuple[str, ...]  # keypoint names (COCO-17, heels, big toes: anny's COCO regressor labels), [joints]
    points: np.ndarray  # [frames, joints, 3] world metres (anything where weight is 0)
    weight: np.ndarray  # [frames, joints] >= 0 (0: not observed)

    def __post_init__(self) -> None:
        f, j = self.weight.shape
        if self.points.shape != (f, j, 3) or len(self.names) != j:
            raise ValueError(f"targets: points {self.points.shape}, weight {self.weight.shape}, {len(self.names)} "
                             "names disagree")

    def select(self, names: tuple[str, ...]) -> "KeypointTargets":
        """The columns of `names` (each must be one of `self.names`), in that order."""
        idx = [self.names.index(n) for n in names]
        return KeypointTargets(names=tuple(names), points=self.points[:, idx], weight=self.weight[:, idx])


@dataclass(frozen=True)
class ImageKeypointTargets:
    """2D keypoints seen by pinhole cameras (a monocular video: one camera), one row per frame."""

    names: tuple[str, ...]  # [joints] keypoint names
    P: np.ndarray  # [cams, 3, 4] projection matrices K [R | T] of the undistorted cameras, world metres
    focal_px: np.ndarray  # [cams] mean focal length, pixels
    points: np.ndarray  # [frames, cams, joints, 2] pixels (anything where weight is 0)
    weight: np.ndarray  # [frames, cams, joints] >= 0 (the detector's confidence; 0: not observed)

    def __post_init__(self) -> None:
        f, c, j = self.weight.shape
        if (self.points.shape != (f, c, j, 2) or len(self.names) != j or self.P.shape != (c, 3, 4)
                or self.focal_px.shape != (c,)):
            raise ValueError(f"image targets: points {self.points.shape}, weight {self.weight.shape}, P "
                             f"{self.P.shape}, focal {self.focal_px.shape}, {len(self.names)} names disagree")

    def select(self, names: tuple[str, ...]) -> "ImageKeypointTargets":
        idx = [self.names.index(n) for n in names]
        return replace(self, names=tuple(names), points=self.points[:, :, idx], weight=self.weight[:, :, idx])

    def project(self, X: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """world points [frames, n, 3] -> (pixels [frames, cams, n, 2], depth [frames, cams, n])."""
        P = torch.as_tensor(self.P, dtype=X.dtype)
        x = torch.einsum("cij,fnj->fcni", P[..., :3], X) + P[None, :, None, :, 3]
        z = x[..., 2].clamp_min(1e-3)
        return x[..., :2] / z[..., None], z


@dataclass(frozen=True)
class SilhouetteTargets:
    """Person masks of the fitted frames as distance fields, for the silhouette term (see the module docstring).
    Every camera's field is stored on one common grid [H, W] (at most `MAX_FIELD_SIDE` px, resized from the
    camera's own image; sampling uses coordinates normalised by each camera's own image size)."""

    P: np.ndarray  # [cams, 3, 4] pinhole projection matrices K [R | T] of the undistorted cameras, world metres
    image_size: np.ndarray  # [cams, 2] (width, height) of each camera's image, pixels
    focal_px: np.ndarray  # [cams] mean focal length, pixels
    distance: np.ndarray  # [frames, cams, H, W] float32 distance (camera pixels) to the mask; 0 inside
    weight: np.ndarray  # [frames, cams] 1 where the view has a mask, 0 where it has none (left out)

    def __post_init__(self) -> None:
        f, c = self.weight.shape
        if (self.P.shape != (c, 3, 4) or self.image_size.shape != (c, 2) or self.focal_px.shape != (c,)
                or self.distance.ndim != 4 or self.distance.shape[:2] != (f, c)):
            raise ValueError(f"silhouettes: P {self.P.shape}, image_size {self.image_size.shape}, focal_px "
                             f"{self.focal_px.shape}, distance {self.distance.shape}, weight {self.weight.shape} "
                             "disagree")


def mask_distance(mask: np.ndarray, grid: tuple[int, int]) -> np.ndarray:
    """bool [height, width] person mask -> float32 [H, W] = `grid`: Euclidean distance (in the mask's pixels) of
    each pixel to the nearest mask pixel, 0 inside (OpenCV `distanceTransform`, exact L2), area-resized to the
    grid. An empty mask is an error (leave the view out instead)."""
    import cv2

    m = np.asarray(mask, dtype=bool)
    if not m.any():
        raise ValueError("mask_distance: empty mask")
    d = cv2.distanceTransform((~m).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    if d.shape != grid:
        d = cv2.resize(d, (grid[1], grid[0]), interpolation=cv2.INTER_AREA)
    return d.astype(np.float32)


def field_grid(width: int, height: int) -> tuple[int, int]:
    """(H, W) of the distance-field grid for a camera of `width` x `height` px: its size, shrunk so the larger
    side is at most `MAX_FIELD_SIDE`."""
    s = min(1.0, MAX_FIELD_SIDE / max(width, height))
    return max(1, round(height * s)), max(1, round(width * s))


@dataclass(frozen=True)
class SilhouetteReport:
    """How the silhouette term moved the fit: share of projected vertices (the term's subset) inside the masks
    (1 px tolerance), over the views with a mask, and the masks' outline's mean distance to the projected body."""

    inside_before: float  # when the term switched on
    inside_after: float  # at the end of the fit
    outline_before_m: float = float("nan")  # mean distance (metres at the subject) of the masks' outline points to
    outline_after_m: float = float("nan")  # the nearest projected vertex, idem (NaN: the outline term was off)
    outline_on: bool = False  # the outline term ran (False: weight 0, or the gate kept it off: loose clothing)

    def to_json(self) -> dict[str, float | None]:
        def num(x: float) -> float | None:
            return round(x, 4) if np.isfinite(x) else None

        return {"inside_before": num(self.inside_before), "inside_after": num(self.inside_after),
                "outline_before_m": num(self.outline_before_m), "outline_after_m": num(self.outline_after_m),
                "outline_on": self.outline_on}


@dataclass(frozen=True)
class KeypointFit:
    motion: BodyMotion  # the fitted parameters, one row per target frame (frame_index 0..frames-1)
    names: tuple[str, ...]  # [joints] the keypoints fitted (those of the targets the body model provides)
    error_m: np.ndarray  # [frames] weighted mean distance of the fitted keypoints to the targets (metres)
    seconds: float
    silhouette: SilhouetteReport | None = None  # None when the term was off (no silhouettes or weight 0)
    error_px: np.ndarray | None = None  # [frames] 2D targets: weighted mean reprojection error (pixels)
    height_m: float = float("nan")  # the fitted subject's standing height (reference pose), metres
    ground: np.ndarray | None = None  # [4] the fitted floor plane (n [3] unit up, d): n·x = d (ground term only)

    def to_motion(self, frame_index, fps: float = 30.0) -> BodyMotion:
        return replace(self.motion, frame_index=np.asarray(frame_index), fps=fps)


class KeypointBody(Protocol):
    """The body-model-specific part of the keypoint fit (see the module docstring)."""

    body_model: str  # "anny" | "smpl" | "smplx"
    names: tuple[str, ...]  # [joints] the keypoints it provides (of those asked for, in that order)
    weight: np.ndarray  # [joints] relative weight of each keypoint in the data term
    num_rotations: int  # rotation vectors per frame (the root excluded)
    num_shape: int  # shape parameters, shared over frames
    dtype: torch.dtype

    def keypoints(self, rotvecs: torch.Tensor, R_root: torch.Tensor, t_root: torch.Tensor,
                  shape: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """rotvecs [frames, rotations, 3], R_root [frames, 3, 3], t_root [frames, 3] (a point rigid with the root
        goes to R_root x + t_root), shape [num_shape] -> (keypoints [frames, joints, 3], vertices [frames, V, 3])
        world metres, differentiable."""
        ...

    def shape_prior(self, shape: torch.Tensor) -> torch.Tensor:
        """P(s): a scalar, zero for the average subject (s = 0)."""
        ...

    def limit_penalty(self, rotvecs: torch.Tensor) -> torch.Tensor:
        """L(θ) of the module docstring per frame: rotvecs [frames, rotations, 3] -> [frames] (zeros: no limits)."""
        ...

    def to_motion(self, rotvecs: torch.Tensor, R_root: torch.Tensor, t_root: torch.Tensor,
                  shape: torch.Tensor) -> BodyMotion:
        """The parameters as the body model's `BodyMotion` (frame_index 0..frames-1)."""
        ...


def keypoint_body(body, names: tuple[str, ...],
                  offsets: "dict[str, tuple[str, tuple[float, float, float]]] | None" = None) -> KeypointBody:
    """The `KeypointBody` of a loaded body model (`AnnyBody` or `SmplBody`) for the keypoint `names`. `offsets`
    (anny only; see `AnnyKeypoints`): a detector's keypoint definitions against anny's COCO regressor."""
    if body.name == "anny":
        return AnnyKeypoints(body, names, offsets=offsets)
    if body.name in ("smpl", "smplx"):
        from avatarctl.body.smpl_keypoints import SmplKeypoints

        return SmplKeypoints(body, names)
    raise ValueError(f"no keypoint fit for the {body.name} body model (anny, smpl, smplx)")


class AnnyKeypoints(torch.nn.Module):
    """Differentiable keypoints of anny: (rotvecs [frames, bones, 3], root R [frames, 3, 3], root t [frames, 3],
    phenotype [P]) -> [frames, joints, 3] metres, for the keypoint `names` (labels of `KeypointsRegressor.coco`).

    `offsets` {name: (bone, (x, y, z) metres)}: where a detector puts keypoint `name` relative to anny's COCO point,
    in the rest frame of `bone` (anny's canonical axes: +x the subject's left, +y back, +z up). The keypoint becomes
    K_j + R_b o_j, R_b the bone's rotation from rest to the pose (the rotation of its skinning transform, Eq. 1), so
    the offset turns with the bone (a head's ear offset with the head). MediaPipe's: `ingest.keypoints`."""

    def __init__(self, body, names: tuple[str, ...], bones: tuple[str, ...] = FIT_BONES,
                 offsets: "dict[str, tuple[str, tuple[float, float, float]]] | None" = None):
        super().__init__()
        from anny.keypoints import KeypointsRegressor

        self.body = body
        self.regressor = KeypointsRegressor.coco(body.model)
        labels = list(self.regressor.labels)
        missing = [n for n in names if n not in labels]
        if missing:
            raise ValueError(f"anny's COCO regressor has no keypoints {missing}; it has {labels}")
        self.kp_index = torch.tensor([labels.index(n) for n in names])
        self.bone_index = torch.tensor([body.joint_names.index(b) for b in bones])
        self.n_bones = len(body.joint_names)
        self.body_model = "anny"
        self.names = tuple(names)
        self.weight = np.ones(len(names))
        self.num_rotations = len(bones)
        self.num_shape = len(body.phenotype_labels)
        self.dtype = torch.float64
        self.hinges = _anny_hinges(body, bones)
        offsets = {n: o for n, o in (offsets or {}).items() if n in names}
        unknown = sorted({b for b, _ in offsets.values()} - set(body.joint_names))
        if unknown:
            raise ValueError(f"keypoint offsets name bones anny does not have: {unknown}")
        self.offset_index = torch.tensor([names.index(n) for n in offsets], dtype=torch.long)  # [O] keypoints
        self.offset_bone = torch.tensor([body.joint_names.index(b) for b, _ in offsets.values()], dtype=torch.long)
        self.offset = torch.tensor([o for _, o in offsets.values()], dtype=self.dtype).reshape(-1, 3)  # [O, 3] m

    def pose_matrices(self, rotvecs: torch.Tensor, R_root: torch.Tensor, t_root: torch.Tensor) -> torch.Tensor:
        """[frames, 104, 4, 4] local-ref deltas: identity except the fitted bones' rotations and the root pose."""
        import roma

        f = rotvecs.shape[0]
        rot = torch.eye(3, dtype=rotvecs.dtype).repeat(f, self.n_bones, 1, 1)
        rot = rot.index_put((torch.arange(f)[:, None], self.bone_index[None]), roma.rotvec_to_rotmat(rotvecs))
        rot = torch.cat([R_root[:, None], rot[:, 1:]], dim=1)
        trans = torch.zeros(f, self.n_bones, 3, 1, dtype=rotvecs.dtype)
        trans = torch.cat([t_root[:, None, :, None], trans[:, 1:]], dim=1)
        top = torch.cat([rot, trans], dim=-1)  # [frames, 104, 3, 4]
        bottom = torch.tensor([0, 0, 0, 1], dtype=rotvecs.dtype).expand(f, self.n_bones, 1, 4)
        return torch.cat([top, bottom], dim=-2)

    def forward(self, pose: torch.Tensor, phenotype: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """pose [frames, 104, 4, 4], phenotype [P] -> (keypoints [frames, joints, 3], vertices [frames, V, 3])."""
        labels = self.body.phenotype_labels
        out = self.body.model(pose_parameters=pose, phenotype_kwargs={k: phenotype[i:i + 1] for i, k in
                                                                      enumerate(labels)})
        K = self.regressor(out)[:, self.kp_index]
        if len(self.offset_index):
            b = self.offset_bone
            R = out["bone_poses"][:, b, :3, :3] @ out["rest_bone_poses"][:, b, :3, :3].transpose(-1, -2)  # [f, O]
            o = torch.einsum("foij,oj->foi", R, self.offset.to(K.dtype))
            K = K.index_add(1, self.offset_index, o)
        return K, out["vertices"]

    # ---- KeypointBody: shape s = the phenotype's logits ----
    def keypoints(self, rotvecs: torch.Tensor, R_root: torch.Tensor, t_root: torch.Tensor,
                  shape: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self(self.pose_matrices(rotvecs, R_root, t_root), torch.sigmoid(shape))

    def shape_prior(self, shape: torch.Tensor) -> torch.Tensor:
        return ((torch.sigmoid(shape) - 0.5) ** 2).sum()

    def limit_penalty(self, rotvecs: torch.Tensor) -> torch.Tensor:
        """[frames, bones, 3] -> [frames]: L(θ) of the module docstring over `ANNY_HINGES`."""
        h = self.hinges
        if h is None:
            return rotvecs.new_zeros(rotvecs.shape[0])
        axis, lo, hi, off = (x.to(rotvecs.dtype) for x in (h.axis, h.lo, h.hi, h.off))
        th = rotvecs[:, h.slot]  # [frames, H, 3]
        phi = (th * axis).sum(-1)  # [frames, H] flexion angle
        perp = (th - phi[..., None] * axis).norm(dim=-1)  # [frames, H] rotation off the axis
        return (torch.relu(lo - phi) ** 2 + torch.relu(phi - hi) ** 2 + torch.relu(perp - off) ** 2).sum(-1)

    def to_motion(self, rotvecs: torch.Tensor, R_root: torch.Tensor, t_root: torch.Tensor,
                  shape: torch.Tensor) -> BodyMotion:
        pose = self.pose_matrices(rotvecs, R_root, t_root)
        return BodyMotion(body_model="anny", frame_index=np.arange(rotvecs.shape[0]), pose_parameters=pose.numpy(),
                          phenotype=torch.sigmoid(shape).numpy(), phenotype_labels=self.body.phenotype_labels)


@dataclass(frozen=True)
class Hinges:
    """The hinge joints of `ANNY_HINGES` among the fitted bones (radians)."""

    slot: torch.Tensor  # [H] long: index in the fitted bones
    axis: torch.Tensor  # [H, 3] unit flexion axis
    lo: torch.Tensor  # [H] lower flexion limit
    hi: torch.Tensor  # [H] upper flexion limit
    off: torch.Tensor  # [H] limit of the rotation off the axis (inf: none)


def _anny_hinges(body, bones: tuple[str, ...]) -> Hinges | None:
    """`ANNY_HINGES` of the fitted `bones` as tensors, built once (None: no hinge among them)."""
    rows = [h for h in ANNY_HINGES if h[0] in bones]
    if not rows:
        return None
    orient = torch.as_tensor(np.asarray(body.model.reference_bone_orientations), dtype=torch.float64)

    def axis(bone: str, kind: str) -> torch.Tensor:
        if kind == "x":
            return torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
        own = orient[body.joint_names.index(bone)][:, 0]
        return own / own.norm()

    def radians(degrees: list[float]) -> torch.Tensor:
        return torch.tensor(np.deg2rad(degrees), dtype=torch.float64)

    return Hinges(slot=torch.tensor([bones.index(b) for b, *_ in rows]),
                  axis=torch.stack([axis(b, kind) for b, kind, *_ in rows]),
                  lo=radians([lim[0] for _, _, lim, _ in rows]), hi=radians([lim[1] for _, _, lim, _ in rows]),
                  off=radians([np.inf if off is None else off for *_, off in rows]))


def initial_root(rest: np.ndarray, targets: KeypointTargets) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame root (R [frames, 3, 3], t [frames, 3]) aligning the reference pose's torso keypoints (`rest`
    [joints, 3]) to the targets; frames with fewer than three torso points use every observed keypoint."""
    torso = np.array([n in TORSO for n in targets.names])
    Rs, ts = [], []
    for f in range(targets.points.shape[0]):
        w = targets.weight[f] * torso
        if (w > 0).sum() < 3:
            w = targets.weight[f]
        R, t = rigid_align(rest, targets.points[f], w)
        Rs.append(R)
        ts.append(t)
    return np.stack(Rs), np.stack(ts)


FEET = ("left_heel", "right_heel", "left_big_toe", "right_big_toe")
HEADING_CANDIDATES = 24  # headings tried per frame by `initial_root_2d` (every 15 degrees)
HEADING_STEP_COST = 5e-4  # DP cost of a change of heading by one candidate step between frames (the
# frame cost is the mean squared reprojection error over the squared torso length: a 15-degree error costs ~1e-3)


def body_up(rest: np.ndarray, names: tuple[str, ...]) -> np.ndarray:
    """[3] unit up axis of a reference pose's keypoints [joints, 3]: mid-hips -> mid-shoulders."""
    j = {n: rest[i] for i, n in enumerate(names)}
    up = (j["left_shoulder"] + j["right_shoulder"]) / 2 - (j["left_hip"] + j["right_hip"]) / 2
    return up / np.linalg.norm(up)


def _axis_rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * (K @ K)


def back_project(P: np.ndarray, x: np.ndarray, depth: float) -> np.ndarray:
    """World points [n, 3] at `depth` (metres along the camera's z) on the rays of pixels x [n, 2], P [3, 4]."""
    M, p4 = P[:, :3], P[:, 3]
    h = np.concatenate([x, np.ones((x.shape[0], 1))], axis=1) * depth  # [n, 3]
    return np.linalg.solve(M, (h - p4).T).T


def initial_root_2d(rest: np.ndarray, targets: ImageKeypointTargets, scale: float = 1.0
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame root (R [frames, 3, 3], t [frames, 3]) from 2D keypoints in the first view of `targets`; `rest`
    [joints, 3] the reference pose's keypoints (names of `targets`), `scale` the subject's size over the reference
    pose's. Depth: the torso (shoulder-hip) length in the image against the reference pose's (heading-invariant for
    an upright body); the torso points are back-projected to that depth and aligned (Kabsch); then the heading about
    the body's up axis is chosen among `HEADING_CANDIDATES` by the reprojection error of every keypoint, made
    consistent over frames by dynamic programming (a change of k steps costs k² `HEADING_STEP_COST`)."""
    names = targets.names
    P = targets.P[0]
    x, w = targets.points[:, 0], targets.weight[:, 0]  # [frames, joints, 2], [frames, joints]
    idx = {n: names.index(n) for n in TORSO}
    sides = (("left_shoulder", "left_hip"), ("right_shoulder", "right_hip"))
    rest_len = scale * np.mean([np.linalg.norm(rest[idx[a]] - rest[idx[b]]) for a, b in sides])
    up = body_up(rest, names)
    torso = np.array([n in TORSO for n in names])
    f_px = float(targets.focal_px[0])
    frames = x.shape[0]
    depth = np.full(frames, np.nan)
    for f in range(frames):
        lens = [np.linalg.norm(x[f, idx[a]] - x[f, idx[b]]) for a, b in sides if w[f, idx[a]] > 0 and w[f, idx[b]] > 0]
        if lens and max(lens) > 1:
            depth[f] = f_px * rest_len / max(lens)  # the longer side: foreshortening only shortens
    fill = np.nanmedian(depth) if np.isfinite(depth).any() else 3.0
    depth = np.where(np.isfinite(depth), depth, fill)
    n_k = HEADING_CANDIDATES
    Rs = np.zeros((frames, n_k, 3, 3))
    ts = np.zeros((frames, n_k, 3))
    cost = np.zeros((frames, n_k))
    for f in range(frames):
        wt = w[f] * torso
        if (wt > 0).sum() < 3:
            wt = w[f]
        X = back_project(P, np.nan_to_num(x[f]), depth[f])
        R0, _ = rigid_align(rest * scale, X, wt)
        wn = wt / wt.sum()
        c_dst = (wn[:, None] * X).sum(0)
        c_src = (wn[:, None] * rest * scale).sum(0)
        for k in range(n_k):
            R = R0 @ _axis_rotation(up, 2 * np.pi * k / n_k)
            t = c_dst - R @ c_src
            Y = (rest * scale) @ R.T + t
            h = Y @ P[:, :3].T + P[:, 3]
            uv = h[:, :2] / np.maximum(h[:, 2:], 1e-3)
            err = ((uv - x[f]) ** 2).sum(-1) * (w[f] > 0)
            norm = max((f_px * rest_len / depth[f]) ** 2, 1e-9)
            cost[f, k] = (w[f] * np.nan_to_num(err)).sum() / max(w[f].sum(), 1e-9) / norm
            Rs[f, k], ts[f, k] = R, c_dst - R @ (c_src / scale)  # the average subject, centred on the torso
    steps = np.abs(np.arange(n_k)[:, None] - np.arange(n_k)[None])
    trans = HEADING_STEP_COST * np.minimum(steps, n_k - steps) ** 2  # [k_prev, k]
    acc, back = cost[0].copy(), np.zeros((frames, n_k), dtype=np.int64)
    for f in range(1, frames):
        tot = acc[:, None] + trans
        back[f] = tot.argmin(0)
        acc = tot.min(0) + cost[f]
    best = np.zeros(frames, dtype=np.int64)
    best[-1] = int(acc.argmin())
    for f in range(frames - 1, 0, -1):
        best[f - 1] = back[f, best[f]]
    return Rs[np.arange(frames), best], ts[np.arange(frames), best]


class SilhouetteTerm:
    """The silhouette term's data as tensors, and the term itself (see the module docstring)."""

    def __init__(self, sil: SilhouetteTargets, frames: int, dtype: torch.dtype):
        if sil.weight.shape[0] != frames:
            raise ValueError(f"silhouettes have {sil.weight.shape[0]} frames, keypoint targets {frames}")
        self.P = torch.as_tensor(sil.P, dtype=dtype)  # [cams, 3, 4]
        self.size = torch.as_tensor(sil.image_size, dtype=dtype)  # [cams, 2]
        self.focal = torch.as_tensor(sil.focal_px, dtype=dtype)  # [cams]
        f, c, h, w = sil.distance.shape
        self.field = torch.as_tensor(sil.distance, dtype=torch.float32).reshape(f * c, 1, h, w)
        self.weight = torch.as_tensor(sil.weight, dtype=dtype)  # [frames, cams]
        self._sil = sil
        self._outline: tuple[torch.Tensor, torch.Tensor] | None = None  # built by the outline term's first call

    def outline(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(points [frames, cams, OUTLINE_POINTS, 2] camera pixels, weight [frames, cams, OUTLINE_POINTS]: 1 for a
        point, 0 for padding) of every view's mask outline (`outline_points`), built once."""
        if self._outline is None:
            f, c = self.weight.shape
            pts = torch.zeros(f, c, OUTLINE_POINTS, 2)
            w = torch.zeros(f, c, OUTLINE_POINTS)
            for i in range(f):
                for j in range(c):
                    p = outline_points(self._sil.distance[i, j], self._sil.image_size[j])
                    pts[i, j, :len(p)] = torch.as_tensor(p)
                    w[i, j, :len(p)] = 1
            self._outline = pts, w
        return self._outline

    def project(self, vertices: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """[frames, n, 3] world vertices -> (pixels [frames, cams, n, 2], depth [frames, cams, n])."""
        x = torch.einsum("cij,fnj->fcni", self.P[..., :3], vertices) + self.P[None, :, None, :, 3]  # [f, c, n, 3]
        z = x[..., 2].clamp_min(1e-3)
        return x[..., :2] / z[..., None], z

    def distances(self, vertices: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """[frames, n, 3] world vertices -> (metres outside the mask [frames, cams, n], pixels [frames, cams, n])."""
        f, n, _ = vertices.shape
        c = self.P.shape[0]
        uv, z = self.project(vertices)
        g = (uv + 0.5) / self.size[None, :, None, :] * 2 - 1  # grid_sample's coordinates, align_corners=False
        d = torch.nn.functional.grid_sample(self.field, g.reshape(f * c, 1, n, 2).float(), mode="bilinear",
                                            padding_mode="border", align_corners=False)
        d_px = d.reshape(f, c, n).to(vertices.dtype)
        return d_px * z / self.focal[None, :, None], d_px

    def loss(self, vertices: torch.Tensor, scale_m: float) -> torch.Tensor:
        """Mean over the views with a mask and the vertices of ρ_s(metres outside)."""
        r, _ = self.distances(vertices)
        s2 = scale_m ** 2
        per_view = (s2 * r ** 2 / (r ** 2 + s2)).mean(-1)  # [f, c]
        return (self.weight * per_view).sum() / self.weight.sum().clamp_min(1e-9)

    def outline_distances(self, vertices: torch.Tensor) -> torch.Tensor:
        """[frames, n, 3] world vertices -> [frames, cams, points] metres (at the nearest vertex's depth) from each
        outline point to the nearest projected vertex."""
        uv, z = self.project(vertices)
        d, nearest = torch.cdist(self.outline()[0], uv.float()).min(-1)  # [f, c, points]
        return d.to(vertices.dtype) * torch.gather(z, 2, nearest) / self.focal[None, :, None]

    def outline_loss(self, vertices: torch.Tensor, scale_m: float) -> torch.Tensor:
        """Mean over the views with a mask and their outline points of ρ_s(metres to the projected body)."""
        r = self.outline_distances(vertices)
        s2 = scale_m ** 2
        w = self.outline()[1].to(r.dtype)
        per_view = (w * s2 * r ** 2 / (r ** 2 + s2)).sum(-1) / w.sum(-1).clamp_min(1)  # [f, c]
        return (self.weight * per_view).sum() / self.weight.sum().clamp_min(1e-9)

    def outline_mean(self, vertices: torch.Tensor) -> float:
        """Mean distance (metres) of the outline points to the projected body, views with a mask."""
        with torch.no_grad():
            w = self.outline()[1].to(vertices.dtype) * self.weight[..., None]
            return float((w * self.outline_distances(vertices)).sum() / w.sum().clamp_min(1e-9))

    def inside(self, vertices: torch.Tensor) -> float:
        """Share of the projected vertices within 1 px of the masks (views with a mask)."""
        with torch.no_grad():
            _, d_px = self.distances(vertices)
            share = (d_px <= 1.0).to(vertices.dtype).mean(-1)  # [f, c]
            return float((self.weight * share).sum() / self.weight.sum().clamp_min(1e-9))


def fit_keypoints(model: KeypointBody, targets: KeypointTargets | ImageKeypointTargets,
                  cfg: KeypointFitConfig = KeypointFitConfig(), progress: ProgressFn | None = None,
                  silhouettes: SilhouetteTargets | None = None) -> KeypointFit:
    """Fit the body `model` (a `KeypointBody`, see `keypoint_body`) to `targets`, 3D keypoints or 2D keypoints in
    pinhole views (`ImageKeypointTargets`, the monocular energy); see the module docstring for the energy. Target
    keypoints the model does not provide are left out. Every frame needs at least three observed keypoints (the
    caller drops frames without a person). With `silhouettes` (rows = the targets' frames) and `cfg.w_silhouette`
    > 0 the silhouette term joins from step `cfg.silhouette_start * iters`."""
    import time

    import roma

    t0 = time.perf_counter()
    image = isinstance(targets, ImageKeypointTargets)
    targets = targets.select(model.names)
    seen = (np.asarray(targets.weight) > 0).any(axis=1) if image else np.asarray(targets.weight) > 0
    if seen.sum(axis=1).min(initial=3) < 3:
        raise ValueError("every frame needs at least three observed keypoints")
    dt = model.dtype
    f = targets.points.shape[0]
    X = torch.as_tensor(np.nan_to_num(targets.points), dtype=dt)
    W_obs = torch.as_tensor(targets.weight, dtype=dt)  # [frames, (cams,) joints] the targets' own weights
    W = W_obs * torch.as_tensor(model.weight, dtype=dt)  # ... times the model's relative weights
    zero_pose = (torch.zeros(1, model.num_rotations, 3, dtype=dt), torch.eye(3, dtype=dt)[None],
                 torch.zeros(1, 3, dtype=dt))
    with torch.no_grad():
        rest, rest_v = (a[0].numpy() for a in model.keypoints(*zero_pose, torch.zeros(model.num_shape, dtype=dt)))
    up = body_up(rest, model.names)
    up_t = torch.as_tensor(up, dtype=dt)

    def height(shape: torch.Tensor) -> torch.Tensor:
        h = model.keypoints(*zero_pose, shape)[1][0] @ up_t
        return h.max() - h.min()

    if image:
        scale = 1.0 if cfg.height_m is None else cfg.height_m / float(np.ptp(rest_v @ up))
        R0, t0_root = initial_root_2d(rest, targets, scale)
    else:
        R0, t0_root = initial_root(rest, targets)
    root_rv = torch.tensor(roma.rotmat_to_rotvec(torch.as_tensor(R0)).numpy(), dtype=dt, requires_grad=True)
    root_t = torch.tensor(t0_root, dtype=dt, requires_grad=True)
    rotvecs = torch.zeros(f, model.num_rotations, 3, dtype=dt, requires_grad=True)
    shape = torch.zeros(model.num_shape, dtype=dt, requires_grad=cfg.fit_shape)
    params = [root_rv, root_t, rotvecs] + ([shape] if cfg.fit_shape else [])
    opt = torch.optim.Adam(params, lr=cfg.lr)
    s2 = cfg.robust_scale_m ** 2
    wsum = W.sum().clamp_min(1e-9)
    sil = None
    if silhouettes is not None and (cfg.w_silhouette > 0 or cfg.w_outline > 0) \
            and bool((silhouettes.weight > 0).any()):
        sil = SilhouetteTerm(silhouettes, f, dt)
    sil_start = int(cfg.silhouette_start * cfg.iters)
    sub = None  # [n] the term's vertices, chosen on the first forward pass
    inside_before = outline_before = float("nan")
    outline_on = False  # decided at s_0 by the gate
    focal = torch.as_tensor(targets.focal_px, dtype=dt)[None, :, None] if image else None
    feet = [model.names.index(n) for n in FEET if n in model.names]
    feet_seen = np.zeros(f, dtype=bool)
    if feet:
        w_feet = np.asarray(targets.weight)[..., feet]
        feet_seen = ((w_feet.max(axis=1) if image else w_feet) > 0).sum(-1) >= 2
    ground_on = cfg.w_ground > 0 and len(feet) >= 2 and feet_seen.any()
    ground_n = torch.tensor(R0.mean(0) @ up, dtype=dt, requires_grad=True)  # the body's mean up: the floor normal
    ground_d = torch.zeros((), dtype=dt, requires_grad=True)
    if ground_on:
        with torch.no_grad():
            K0, _ = model.keypoints(rotvecs, torch.as_tensor(R0, dtype=dt), root_t, shape)
            n0 = ground_n / ground_n.norm()
            ground_d.fill_((K0[feet_seen][:, feet] @ n0).min(-1).values.median())
        opt.add_param_group({"params": [ground_n, ground_d], "lr": cfg.lr})
    feet_rows = torch.as_tensor(np.nonzero(feet_seen)[0])

    def data_term(K: torch.Tensor) -> torch.Tensor:
        if not image:
            r2 = ((K - X) ** 2).sum(-1)
        else:  # reprojection error in metres at the subject: pixels x depth / focal
            uv, z = targets.project(K)
            r2 = ((uv - X) ** 2).sum(-1) * (z / focal) ** 2
        return (W * s2 * r2 / (r2 + s2)).sum() / wsum

    for it in range(cfg.iters):
        opt.zero_grad()
        R_root = roma.rotvec_to_rotmat(root_rv)
        K, V = model.keypoints(rotvecs, R_root, root_t, shape)
        loss = data_term(K)
        if cfg.height_m is not None and cfg.w_height > 0:
            loss = loss + cfg.w_height * (height(shape) - cfg.height_m) ** 2
        if ground_on:
            n = ground_n / ground_n.norm()
            lowest = (K[feet_rows][:, feet] @ n).min(-1).values  # [frames with feet]
            loss = loss + cfg.w_ground * ((lowest - ground_d) ** 2).mean()
        if cfg.w_root_smooth > 0 and f > 1:
            loss = loss + cfg.w_root_smooth * ((R_root[1:] - R_root[:-1]) ** 2).sum((1, 2)).mean()
        if sil is not None and it >= sil_start:
            if sub is None:
                sub = spread_indices(V.shape[1], cfg.silhouette_vertices)
                if cfg.w_silhouette > 0:
                    inside_before = sil.inside(V[:, sub].detach())
                if cfg.w_outline > 0:
                    outline_before = sil.outline_mean(V[:, sub].detach())
                    outline_on = outline_before <= cfg.outline_gate_m
            if cfg.w_silhouette > 0:
                loss = loss + cfg.w_silhouette * sil.loss(V[:, sub], cfg.silhouette_scale_m)
            if outline_on:
                loss = loss + cfg.w_outline * sil.outline_loss(V[:, sub], cfg.silhouette_scale_m)
        loss = loss + cfg.w_pose * (rotvecs ** 2).sum((1, 2)).mean()
        if f > 1:
            loss = loss + cfg.w_smooth * ((rotvecs[1:] - rotvecs[:-1]) ** 2).sum((1, 2)).mean()
            loss = loss + cfg.w_trans * ((root_t[1:] - root_t[:-1]) ** 2).sum(1).mean()
        loss = loss + cfg.w_shape * model.shape_prior(shape)
        if cfg.w_limits > 0:
            loss = loss + cfg.w_limits * model.limit_penalty(rotvecs).mean()
        loss.backward()
        opt.step()
        if progress is not None:
            progress(ProgressReport(done=it + 1, total=cfg.iters, part="fit"))
    report, err_px = None, None
    with torch.no_grad():
        R = roma.rotvec_to_rotmat(root_rv)
        K, V = model.keypoints(rotvecs, R, root_t, shape)
        if image:
            uv, z = targets.project(K)
            d_px = (uv - X).norm(dim=-1)  # [frames, cams, joints]
            wsum_f = W_obs.sum((1, 2)).clamp_min(1e-9)
            err_px = ((W_obs * d_px).sum((1, 2)) / wsum_f).numpy()
            err = ((W_obs * d_px * z / focal).sum((1, 2)) / wsum_f).numpy()
        else:
            d = (K - X).norm(dim=-1)
            err = ((W_obs * d).sum(1) / W_obs.sum(1).clamp_min(1e-9)).numpy()
        fitted_height = float(height(shape))
        ground = None
        if ground_on:
            n = ground_n / ground_n.norm()
            ground = np.concatenate([n.numpy(), [float(ground_d)]])
        if sil is not None:
            started = sub is not None  # the terms switched on during the fit (iters > s_0)
            sub = spread_indices(V.shape[1], cfg.silhouette_vertices) if sub is None else sub
            after = sil.inside(V[:, sub]) if cfg.w_silhouette > 0 else float("nan")
            outline_after = sil.outline_mean(V[:, sub]) if cfg.w_outline > 0 else float("nan")
            report = SilhouetteReport(inside_before=inside_before if started else after, inside_after=after,
                                      outline_before_m=outline_before if started else outline_after,
                                      outline_after_m=outline_after, outline_on=outline_on)
        motion = model.to_motion(rotvecs, R, root_t, shape)
    return KeypointFit(motion=motion, names=model.names, error_m=err, seconds=time.perf_counter() - t0,
                       silhouette=report, error_px=err_px, height_m=fitted_height, ground=ground)


def outline_points(distance: np.ndarray, image_size: np.ndarray, n: int = OUTLINE_POINTS) -> np.ndarray:
    """float [H, W] distance field of a mask (`mask_distance`, 0 inside) of an image `image_size` (width, height)
    px -> [m <= n, 2] camera-pixel points spread evenly along the mask's outline (the inside's boundary pixels, 3 x 3
    erosion, scan order); none for an empty mask."""
    import cv2

    inside = (np.asarray(distance) <= 0).astype(np.uint8)
    eroded = cv2.erode(inside, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=0)
    ys, xs = np.nonzero(inside & (1 - eroded))
    if len(xs) == 0:
        return np.zeros((0, 2), dtype=np.float32)
    pick = np.linspace(0, len(xs) - 1, min(n, len(xs))).round().astype(np.int64)
    h, w = inside.shape
    return np.stack([(xs[pick] + 0.5) * image_size[0] / w - 0.5,
                     (ys[pick] + 0.5) * image_size[1] / h - 0.5], axis=1).astype(np.float32)


def spread_indices(total: int, n: int) -> torch.Tensor:
    """[min(n, total)] indices spread evenly over range(total) (deterministic)."""
    n = min(n, total)
    return torch.as_tensor(np.linspace(0, total - 1, n).round().astype(np.int64))
