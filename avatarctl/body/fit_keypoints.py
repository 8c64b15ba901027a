"""Fit anny to 3D body keypoints by gradient descent (the "own capture" path: no body fits given).

Model: anny's mesh ``V(θ, φ)`` for per-frame local-ref rotations θ (rotation vectors of `FIT_BONES`; every other
bone stays at anny's reference A-pose) and a root pose ``[R_f | t_f]`` (the root delta acts on the whole body in
world coordinates: ``V = R_f V_ref + t_f``), and one phenotype φ ∈ [0, 1]^6 per subject (sigmoid of free logits).
Keypoints are anny's `KeypointsRegressor.coco`, a fixed convex combination of vertices, ``K = W V`` (differentiable).

Energy minimised with Adam over all frames at once (in the spirit of SMPLify, Bogo et al. 2016, Eq. 1, with 3D
instead of 2D data):

    E = Σ_fj w_fj ρ(‖K_fj − X_fj‖) / Σ w          robust data term, ρ = Geman-McClure with scale σ (metres)
      + λ_pose   · mean_f Σ_b ‖θ_fb‖²             pose prior: stay near the reference pose
      + λ_smooth · mean_f Σ_b ‖θ_f+1,b − θ_fb‖²   temporal smoothness (and λ_trans for root translation)
      + λ_shape  · ‖φ − ½‖²                       phenotype prior: stay near anny's average subject

ρ(r) = σ² r² / (r² + σ²) (Geman & McClure 1987): quadratic for r ≪ σ, bounded for outliers.
Initialisation: θ = 0, φ = ½, and the root by a weighted Kabsch / Umeyama (1991) alignment of the reference
pose's hips and shoulders to the targets of each frame.

World frame of anny: +x subject's left, +y subject's back, +z up, metres. The capture's world frame may be any
orientation: the root rotation absorbs it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch

from avatarctl.body.motion import BodyMotion

FIT_BONES = ("spine05", "spine04", "spine03", "spine02", "spine01", "neck01", "neck02", "neck03", "head",
             "clavicle.L", "clavicle.R", "upperarm01.L", "upperarm01.R", "lowerarm01.L", "lowerarm01.R",
             "upperleg01.L", "upperleg01.R", "lowerleg01.L", "lowerleg01.R", "foot.L", "foot.R")
TORSO = ("left_shoulder", "right_shoulder", "left_hip", "right_hip")


@dataclass(frozen=True)
class KeypointFitConfig:
    iters: int = 400  # Adam steps over all frames
    lr: float = 0.02  # Adam learning rate (rotation vectors in radians, translations in metres, logits)
    robust_scale_m: float = 0.10  # σ of the Geman-McClure data term
    w_pose: float = 1e-5  # λ_pose
    w_smooth: float = 1e-4  # λ_smooth (rotation vectors between consecutive fitted frames)
    w_trans: float = 1e-3  # λ_trans (root translation between consecutive fitted frames)
    w_shape: float = 1e-4  # λ_shape
    fit_phenotype: bool = True  # optimise the subject's phenotype (else anny's average, ½)

    def __post_init__(self) -> None:
        if self.iters < 0 or self.lr <= 0 or self.robust_scale_m <= 0:
            raise ValueError(f"bad keypoint-fit settings {self}")


@dataclass(frozen=True)
class KeypointTargets:
    """3D keypoints to fit, one row per frame."""

    names: tuple[str, ...]  # keypoint names (anny's COCO regressor labels), [joints]
    points: np.ndarray  # [frames, joints, 3] world metres (anything where weight is 0)
    weight: np.ndarray  # [frames, joints] >= 0 (0: not observed)

    def __post_init__(self) -> None:
        f, j = self.weight.shape
        if self.points.shape != (f, j, 3) or len(self.names) != j:
            raise ValueError(f"targets: points {self.points.shape}, weight {self.weight.shape}, {len(self.names)} "
                             "names disagree")


@dataclass(frozen=True)
class KeypointFit:
    pose_parameters: np.ndarray  # [frames, 104, 4, 4] anny local-ref deltas (root delta = world pose)
    phenotype: np.ndarray  # [P] in [0, 1]
    phenotype_labels: tuple[str, ...]
    error_m: np.ndarray  # [frames] weighted mean distance of the fitted keypoints to the targets (metres)
    seconds: float

    def to_motion(self, frame_index, fps: float = 30.0) -> BodyMotion:
        return BodyMotion(body_model="anny", frame_index=np.asarray(frame_index), fps=fps,
                          pose_parameters=self.pose_parameters, phenotype=self.phenotype,
                          phenotype_labels=self.phenotype_labels)


class AnnyKeypoints(torch.nn.Module):
    """Differentiable keypoints of anny: (rotvecs [frames, bones, 3], root R [frames, 3, 3], root t [frames, 3],
    phenotype [P]) -> [frames, joints, 3] metres, for the keypoint `names` (labels of `KeypointsRegressor.coco`)."""

    def __init__(self, body, names: tuple[str, ...], bones: tuple[str, ...] = FIT_BONES):
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
        return self.regressor(out)[:, self.kp_index], out["vertices"]


def kabsch(src: np.ndarray, dst: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted rigid alignment (Kabsch 1976; Umeyama 1991 without scale): R [3, 3], t [3] minimising
    Σ_i w_i ‖R src_i + t − dst_i‖² for src, dst [n, 3], w [n] (needs three non-collinear weighted points)."""
    w = w / w.sum()
    ms, md = (w[:, None] * src).sum(0), (w[:, None] * dst).sum(0)
    H = ((src - ms) * w[:, None]).T @ (dst - md)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    return R, md - R @ ms


def initial_root(rest: np.ndarray, targets: KeypointTargets) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame root (R [frames, 3, 3], t [frames, 3]) aligning the reference pose's torso keypoints (`rest`
    [joints, 3]) to the targets; frames with fewer than three torso points use every observed keypoint."""
    torso = np.array([n in TORSO for n in targets.names])
    Rs, ts = [], []
    for f in range(targets.points.shape[0]):
        w = targets.weight[f] * torso
        if (w > 0).sum() < 3:
            w = targets.weight[f]
        R, t = kabsch(rest, targets.points[f], w)
        Rs.append(R)
        ts.append(t)
    return np.stack(Rs), np.stack(ts)


def fit_anny_keypoints(body, targets: KeypointTargets, cfg: KeypointFitConfig = KeypointFitConfig(),
                       progress: Callable[[int, int], None] | None = None) -> KeypointFit:
    """Fit anny (an `AnnyBody`) to `targets` (see the module docstring for the energy). Every frame needs at
    least three observed keypoints (the caller drops frames without a person)."""
    import time

    import roma

    t0 = time.perf_counter()
    if (np.asarray(targets.weight) > 0).sum(axis=1).min(initial=3) < 3:
        raise ValueError("every frame needs at least three observed keypoints")
    dt = torch.float64
    kp = AnnyKeypoints(body, targets.names)
    labels = body.phenotype_labels
    f = targets.points.shape[0]
    X = torch.as_tensor(np.nan_to_num(targets.points), dtype=dt)
    W = torch.as_tensor(targets.weight, dtype=dt)
    with torch.no_grad():
        eye = torch.eye(3, dtype=dt).expand(1, 3, 3)
        rest = kp(kp.pose_matrices(torch.zeros(1, len(FIT_BONES), 3, dtype=dt), eye, torch.zeros(1, 3, dtype=dt)),
                  torch.full((len(labels),), 0.5, dtype=dt))[0][0].numpy()
    R0, t0_root = initial_root(rest, targets)
    root_rv = torch.tensor(roma.rotmat_to_rotvec(torch.as_tensor(R0)).numpy(), dtype=dt, requires_grad=True)
    root_t = torch.tensor(t0_root, dtype=dt, requires_grad=True)
    rotvecs = torch.zeros(f, len(FIT_BONES), 3, dtype=dt, requires_grad=True)
    logits = torch.zeros(len(labels), dtype=dt, requires_grad=cfg.fit_phenotype)
    params = [root_rv, root_t, rotvecs] + ([logits] if cfg.fit_phenotype else [])
    opt = torch.optim.Adam(params, lr=cfg.lr)
    s2 = cfg.robust_scale_m ** 2
    wsum = W.sum().clamp_min(1e-9)
    for it in range(cfg.iters):
        opt.zero_grad()
        pheno = torch.sigmoid(logits)
        K, _ = kp(kp.pose_matrices(rotvecs, roma.rotvec_to_rotmat(root_rv), root_t), pheno)
        r2 = ((K - X) ** 2).sum(-1)
        loss = (W * s2 * r2 / (r2 + s2)).sum() / wsum
        loss = loss + cfg.w_pose * (rotvecs ** 2).sum((1, 2)).mean()
        if f > 1:
            loss = loss + cfg.w_smooth * ((rotvecs[1:] - rotvecs[:-1]) ** 2).sum((1, 2)).mean()
            loss = loss + cfg.w_trans * ((root_t[1:] - root_t[:-1]) ** 2).sum(1).mean()
        loss = loss + cfg.w_shape * ((pheno - 0.5) ** 2).sum()
        loss.backward()
        opt.step()
        if progress is not None:
            progress(it + 1, cfg.iters)
    with torch.no_grad():
        pheno = torch.sigmoid(logits)
        pose = kp.pose_matrices(rotvecs, roma.rotvec_to_rotmat(root_rv), root_t)
        K, _ = kp(pose, pheno)
        d = (K - X).norm(dim=-1)
        err = ((W * d).sum(1) / W.sum(1).clamp_min(1e-9)).numpy()
    return KeypointFit(pose_parameters=pose.numpy().astype(np.float32), phenotype=pheno.numpy().astype(np.float32),
                       phenotype_labels=tuple(labels), error_m=err, seconds=time.perf_counter() - t0)
