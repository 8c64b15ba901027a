"""One frame's body pose refined against its images with the avatar frozen (issue 51 item 4; `eval --refine-pose`).

Monocular avatar papers (InstantAvatar, GART, Anim-NeRF) score held-out frames after optimising each frame's body
pose against its image, the avatar fixed: an estimated fit is off by a limb's width, and without it the figure mixes
pose error with avatar error. Here, for one frame:

- the corrections are those of `model.pose_refine` (model/pose_refine.py: a rotation delta_j of each refined joint
  about its centre, composed down the kinematic tree, and a root translation tau), one frame's worth, starting at
  zero; the joints refined are those whose subtree carries >= `model.pose_refine.min_share` of the skinning weight,
  about the avatar's own joint centres when it learned pose corrections, else the template's skin-weighted centroids;
- M'_j = D_j M_j drives the frozen avatar (its Delta n / e still conditioned on the unrefined pose: the corrections
  are centimetres), whose Gaussians are rasterized into each given view's crop, through that camera's colour transform;
- the loss is the fit's image loss (`model.losses.image_reconstruction_loss`: L1 + D-SSIM + the mask term, the
  avatar's own lambda_ssim / lambda_mask) plus lambda_pose (|delta|^2 + |tau / 0.1 m|^2), Adam on (delta, tau) only;
  with `target = "masks"` the image loss is the mask term alone, mean |alpha - mask| per view (the avatar's
  silhouette, clothes included, fitted to the frame's masks; its colours are not used);
- coarse to fine: the first half of the steps on the images downsampled 2x (area), the rest at full size; a
  frame whose refined loss (full size) is not below the estimated pose's keeps the estimated pose (Adam's steps of
  about `lr` can only move a pose that is already right: on true fits 40 steps lowered the PSNR of some frames by up
  to 3.5 dB before this rule, none after it; a step decaying to a tenth scored 1 dB lower on estimated fits).

Only the Gaussian local fields (`model.field = gaussians`: a whole crop per step); the ray-marched fields are refused.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch

if TYPE_CHECKING:
    from avatarctl.body.base import BodyTemplate
    from avatarctl.geometry.cameras import Camera
    from avatarctl.io.project_io import ProjectCapture
    from avatarctl.model.avatar import FrameConditioning, NodeState, SlrfAvatar
    from avatarctl.splat import SplatCamera


POSE_TARGETS = ("images", "masks")


@dataclass(frozen=True)
class FramePoseConfig:
    """How one frame's pose is refined (module docstring)."""

    steps: int = 40  # Adam steps (the first half at half resolution)
    lr: float = 5e-3  # Adam's step: radians for delta, metres for tau
    lambda_pose: float = 1e-3  # pull of |delta|^2 + |tau / 0.1 m|^2 towards the estimated pose (per image loss unit)
    target: str = "images"  # what the pose is fitted to: "images" (colours and masks) | "masks" (the masks alone)

    def __post_init__(self) -> None:
        if self.steps < 1 or not self.lr > 0 or self.lambda_pose < 0 or self.target not in POSE_TARGETS:
            raise ValueError(f"FramePoseConfig needs steps >= 1, lr > 0, lambda_pose >= 0, target in "
                             f"{POSE_TARGETS}; got {self}")


@dataclass(frozen=True)
class PoseView:
    """One image of the frame the pose is refined against: the camera of its crop and what it shows."""

    camera: "SplatCamera"  # the crop's camera (`SplatCamera.crop`)
    target: torch.Tensor  # [h, w, 3] ground truth in [0, 1], composited over the background
    mask: torch.Tensor  # [h, w] the subject's mask in [0, 1]
    gain: torch.Tensor | None = None  # [3] the camera's colour transform (None: identity)
    offset: torch.Tensor | None = None  # [3]


@dataclass(frozen=True)
class FramePose:
    """A refined frame: the corrected joint transforms and what the refinement did."""

    joint_transforms: torch.Tensor  # [1, J, 4, 4] M'_j
    delta: np.ndarray  # [J, 3] axis-angle corrections, radians (0 for joints not refined)
    tau: np.ndarray  # [3] root translation, metres
    loss_start: float  # the image loss of the estimated pose (full resolution)
    loss_end: float  # the image loss of the refined pose (full resolution)
    seconds: float

    @property
    def max_angle_deg(self) -> float:
        return float(np.degrees(np.linalg.norm(self.delta, axis=-1).max(initial=0.0)))

    @property
    def shift_cm(self) -> float:
        return float(np.linalg.norm(self.tau) * 100)


def refine_frame_pose(model: "SlrfAvatar", template: "BodyTemplate", cond: "FrameConditioning",
                      views: list[PoseView], background: torch.Tensor, mode: str,
                      cfg: FramePoseConfig = FramePoseConfig(),
                      start_from: tuple[np.ndarray, np.ndarray] | None = None) -> FramePose:
    """Refine the pose of the one frame of `cond` against `views` (module docstring); `template`: the avatar's body
    template; `mode`: the latent mode the frame is rendered with (`SlrfAvatar.node_state`; "sample" is not
    deterministic and is refused). `start_from`: corrections (delta [J, 3], tau [3]) Adam starts from instead of
    zero (a neighbouring frame's, `fit/held_out_poses.py`); the frame then keeps the best of the estimated pose, that
    start and the end."""
    if not model.field_kind.splats:
        raise ValueError(f"pose refinement renders whole crops: it needs model.field 'gaussians', this avatar's is "
                         f"{model.cfg.field!r}")
    if mode == "sample" or cond.joint_transforms.shape[0] != 1 or not views:
        raise ValueError(f"refine_frame_pose needs one frame, a deterministic latent mode and >= 1 view; got "
                         f"{cond.joint_transforms.shape[0]} frames, mode {mode!r}, {len(views)} views")
    t0 = time.perf_counter()
    dev = model.node_rest.device
    refine = _refinement(model, template).to(dev)
    params = [refine.delta, refine.tau]
    opt = torch.optim.Adam(params, lr=cfg.lr)
    one = torch.zeros(1, dtype=torch.long, device=dev)
    bg = background.to(dev, torch.float32)
    coarse = [_downsampled(v, 2) for v in views]

    def loss_of(vs: list[PoseView]) -> torch.Tensor:
        joints = refine(cond.joint_transforms.to(dev, torch.float32), one)
        state = model.node_state(_with_joints(cond, joints), mode=mode)
        rgb, alpha = _render(model, state, vs, bg)
        fit = _mask_loss(alpha, vs) if cfg.target == "masks" else _image_loss(model, rgb, alpha, vs)
        return fit + cfg.lambda_pose * refine.penalty(one)

    with torch.no_grad():
        start = float(loss_of(views))
        best = (start, refine.delta.clone(), refine.tau.clone())  # the estimated pose (zero corrections)
        if start_from is not None:
            refine.delta.copy_(torch.as_tensor(start_from[0], dtype=torch.float32, device=dev)[None])
            refine.tau.copy_(torch.as_tensor(start_from[1], dtype=torch.float32, device=dev)[None])
            warm = float(loss_of(views))
            if warm < best[0]:
                best = (warm, refine.delta.clone(), refine.tau.clone())
    for step in range(cfg.steps):
        loss = loss_of(coarse if step < cfg.steps // 2 else views)
        grads = torch.autograd.grad(loss, params)  # the avatar's weights get no gradient
        for p, g in zip(params, grads):
            p.grad = g
        opt.step()
    with torch.no_grad():
        end = float(loss_of(views))
        if not end < best[0]:  # no better than the estimated pose (or the start given): keep that
            end = best[0]
            refine.delta.copy_(best[1])
            refine.tau.copy_(best[2])
        joints = refine(cond.joint_transforms.to(dev, torch.float32), one)
    delta = (refine.delta[0] * refine.active[:, None]).detach().cpu().numpy()
    return FramePose(joint_transforms=joints.detach(), delta=delta, tau=refine.tau[0].detach().cpu().numpy(),
                     loss_start=start, loss_end=end, seconds=time.perf_counter() - t0)


def corrected_joints(model: "SlrfAvatar", template: "BodyTemplate", M: torch.Tensor, delta: torch.Tensor,
                     tau: torch.Tensor) -> torch.Tensor:
    """[1, J, 4, 4] M'_j = D_j M_j of one frame from its joint transforms `M` [1, J, 4, 4] and the corrections of a
    `FramePose` (`delta` [J, 3], `tau` [3]), about the same joints and centres as `refine_frame_pose`."""
    dev = M.device
    refine = _refinement(model, template).to(dev)
    with torch.no_grad():
        refine.delta.copy_(delta.to(dev, torch.float32)[None])
        refine.tau.copy_(tau.to(dev, torch.float32)[None])
        return refine(M.to(torch.float32), torch.zeros(1, dtype=torch.long, device=dev)).detach()


def crop_views(capture: "ProjectCapture", frame: int, views: list[str], cams: dict[str, "Camera"],
               verts: np.ndarray, background: tuple[float, float, float], device: torch.device, *, pad: float,
               protocol: str = "bbox", colours: dict[str, tuple[np.ndarray, np.ndarray] | None] | None = None,
               images: bool = True) -> list[PoseView]:
    """The `PoseView` of each of `views` (pinhole `cams`) at `frame`: the bbox protocol's crop around the posed body
    `verts` [V, 3] grown by `pad` metres (`protocol` "full": the whole image), its masked image over `background`
    (zeros with `images` False: the masks alone are read) and mask, through `colours[view]` (gain, offset) if any."""
    from avatarctl.evaluate.protocols import bbox_region, full_region, ground_truth
    from avatarctl.splat import SplatCamera

    out = []
    for view in views:
        cam = cams[view]
        region = bbox_region(cam, verts, pad=pad) if protocol == "bbox" else full_region(cam.height, cam.width)
        x0, y0, x1, y1 = region.crop
        whole = capture.mask(view, frame)
        mask = np.ascontiguousarray(whole[y0:y1, x0:x1], np.float32)
        gt = ground_truth(capture.image(view, frame), whole, background)[y0:y1, x0:x1] \
            if images else np.zeros(mask.shape + (3,), np.float32)
        colour = (colours or {}).get(view)
        out.append(PoseView(
            camera=SplatCamera.from_camera(cam, device=device).crop(x0, y0, x1 - x0, y1 - y0),
            target=torch.from_numpy(np.ascontiguousarray(gt, np.float32)).to(device),
            mask=torch.from_numpy(mask).to(device),
            gain=None if colour is None else torch.tensor(colour[0], dtype=torch.float32),
            offset=None if colour is None else torch.tensor(colour[1], dtype=torch.float32)))
    return out


def refined_state(model: "SlrfAvatar", cond: "FrameConditioning", pose: FramePose, mode: str) -> "NodeState":
    """The frame's node state with the refined joint transforms (no gradient)."""
    with torch.no_grad():
        return model.node_state(_with_joints(cond, pose.joint_transforms), mode=mode)


def _refinement(model: "SlrfAvatar", tpl: "BodyTemplate") -> torch.nn.Module:
    """A one-frame `PoseRefinement` on the avatar's joints (module docstring: which joints, about which centres)."""
    from avatarctl.body.joints import skin_weighted_centroids
    from avatarctl.model.pose_refine import PoseRefinement, subtree_share

    learned = model.pose_refine
    if learned is not None:
        refine = PoseRefinement(1, learned.parents, active=learned.active)
        refine.set_centres(learned.centres)
        return refine
    refine = PoseRefinement(1, tpl.parents, active=subtree_share(tpl.skin_weights.float(), tpl.parents)
                            >= model.cfg.pose_refine.min_share)
    refine.set_centres(skin_weighted_centroids(tpl.vertices.float(), tpl.skin_weights.float()))
    return refine


def _with_joints(cond: "FrameConditioning", joints: torch.Tensor) -> "FrameConditioning":
    from dataclasses import replace

    return replace(cond, joint_transforms=joints)


def _render(model: "SlrfAvatar", state: "NodeState", views: list[PoseView], bg: torch.Tensor
            ) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    """Every view's crop rasterized (one batch: the frame's Gaussians repeated per view), through its colour."""
    from avatarctl.evaluate.colour import apply_colour
    from avatarctl.model.avatar import NodeState

    B = len(views)
    batched = NodeState(transforms=state.transforms.expand(B, -1, -1, -1), centers=state.centers.expand(B, -1, -1),
                        delta_n=state.delta_n.expand(B, -1, -1), embed=state.embed.expand(B, -1, -1))
    rgb, alpha = model.render_images(model.posed_gaussians(batched), [v.camera for v in views], bg)
    rgb = [c if v.gain is None else apply_colour(c, a, bg, v.gain.to(c), v.offset.to(c))
           for c, a, v in zip(rgb, alpha, views)]
    return rgb, alpha


def _image_loss(model: "SlrfAvatar", rgb: list[torch.Tensor], alpha: list[torch.Tensor], views: list[PoseView]
                ) -> torch.Tensor:
    from avatarctl.model.losses import image_reconstruction_loss

    g = model.cfg.gaussians
    return image_reconstruction_loss(rgb, [v.target for v in views], alpha, [v.mask for v in views], g.lambda_ssim,
                                     g.lambda_mask, reference_rays=1)[0]


def _mask_loss(alpha: list[torch.Tensor], views: list[PoseView]) -> torch.Tensor:
    """`target = "masks"`: the mean over views of mean |alpha - mask| (module docstring)."""
    return torch.stack([(a - v.mask.to(a.dtype)).abs().mean() for a, v in zip(alpha, views, strict=True)]).mean()


def _downsampled(view: PoseView, f: int) -> PoseView:
    """The view at 1/f of its size: images averaged over f x f pixels, the camera's pixels f times larger
    (`geometry.cameras.scaled_intrinsics`)."""
    from dataclasses import replace

    import torch.nn.functional as F

    from avatarctl.geometry.cameras import scaled_intrinsics

    h, w = view.mask.shape
    if h < 4 * f or w < 4 * f:
        return view
    h2, w2 = h // f, w // f
    target = F.avg_pool2d(view.target[:h2 * f, :w2 * f].permute(2, 0, 1)[None], f)[0].permute(1, 2, 0)
    mask = F.avg_pool2d(view.mask[:h2 * f, :w2 * f][None, None].float(), f)[0, 0]
    return replace(view, camera=replace(view.camera, K=scaled_intrinsics(view.camera.K, 1.0 / f), width=w2, height=h2),
                   target=target, mask=mask)
