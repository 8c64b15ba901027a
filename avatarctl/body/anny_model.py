"""The anny body model (Apache-2.0 code, CC0 assets): the free default.

Wraps `anny.Anny()` (rig "anny": 104 bones, topology "anny": 13,718 vertices). Pose parameters are anny's
"local-ref" deltas [frames, 104, 4, 4], passed through unchanged; the phenotype (gender, age, muscle, weight,
height, proportions in [0, 1]) is per subject. Canonical space = anny's rest mesh for the phenotype.
World frame of anny: +x subject's left, +y subject's back, +z up, metres.

The first `anny.Anny()` on a machine builds a ~790 MB cache (`ANNY_CACHE_DIR`, default ~/.cache/anny).
"""

from __future__ import annotations

import functools
from dataclasses import replace

import numpy as np
import torch

from avatarctl.body.base import BodyTemplate, PosedBody
from avatarctl.body.lbs import matrix_to_axis_angle
from avatarctl.body.motion import BodyMotion


@functools.lru_cache(maxsize=2)
def _anny(device: str):
    from avatarctl.device import init_warp

    init_warp()  # anny compiles Warp kernels: Warp initialised the project's way first
    import anny  # heavy: imported only when a body is needed

    return anny.Anny().to(device)


class AnnyBody:
    """`BodyModel` for anny."""

    name = "anny"

    def __init__(self, device: str = "cpu"):
        self.device = device
        self.model = _anny(device)
        self.joint_names = tuple(str(s) for s in self.model.bone_labels)
        self.parents = tuple(int(p) for p in self.model.bone_parents)
        self.phenotype_labels = tuple(str(s) for s in self.model.phenotype_labels)

    # ---- helpers --------------------------------------------------------------------------------------------
    def _phenotype(self, motion: BodyMotion | None) -> torch.Tensor:
        """[1, P] phenotype in anny's label order (missing labels, or no motion, default to anny's 0.5)."""
        vals = {lab: 0.5 for lab in self.phenotype_labels}
        if motion is not None and motion.phenotype is not None:
            labels = motion.phenotype_labels or self.phenotype_labels
            if len(labels) != len(motion.phenotype):
                raise ValueError(f"{len(motion.phenotype)} phenotype values but {len(labels)} labels")
            for lab, v in zip(labels, motion.phenotype):
                if lab not in vals:
                    raise ValueError(f"unknown anny phenotype label {lab!r}; expected {self.phenotype_labels}")
                vals[lab] = float(v)
        return torch.tensor([[vals[lab] for lab in self.phenotype_labels]], dtype=torch.float64, device=self.device)

    def dense_skin_weights(self) -> torch.Tensor:
        """[V, J] dense skinning weights from anny's sparse (index, weight) pairs."""
        idx = self.model.vertex_bone_indices.long()
        w = self.model.vertex_bone_weights.double()
        dense = torch.zeros(idx.shape[0], len(self.parents), dtype=torch.float64, device=idx.device)
        dense.scatter_add_(1, idx, w)
        return dense

    def faces(self) -> torch.Tensor:
        f = self.model.get_triangular_faces() if callable(getattr(self.model, "get_triangular_faces", None)) \
            else self.model.faces
        return torch.as_tensor(f, dtype=torch.int64).reshape(-1, 3)

    # ---- BodyModel --------------------------------------------------------------------------------------------
    def run(self, motion: BodyMotion, chunk: int = 256) -> dict[str, torch.Tensor]:
        """Raw anny outputs (float64) for every frame, evaluated in chunks."""
        pheno = self._phenotype(motion)
        pp = torch.as_tensor(motion.pose_parameters, dtype=torch.float64, device=self.device)
        outs: dict[str, list[torch.Tensor]] = {}
        with torch.no_grad():
            for s in range(0, pp.shape[0], chunk):
                o = self.model(pose_parameters=pp[s:s + chunk], phenotype_kwargs=pheno)
                for k in ("vertices", "bone_poses"):
                    outs.setdefault(k, []).append(o[k])
                rest = o
        res = {k: torch.cat(v) for k, v in outs.items()}
        res["rest_vertices"] = rest["rest_vertices"][0]
        res["rest_bone_poses"] = rest["rest_bone_poses"][0]
        return res

    def _reference(self, motion: BodyMotion | None) -> dict[str, torch.Tensor]:
        """anny's outputs for identity deltas (the reference pose at the origin) and `motion`'s phenotype."""
        pheno = self._phenotype(motion)
        with torch.no_grad():
            return self.model(pose_parameters=torch.eye(4, dtype=torch.float64, device=self.device)
                              .expand(1, 104, 4, 4), phenotype_kwargs=pheno)

    def reference_heads(self, motion: BodyMotion | None = None) -> np.ndarray:
        """[104, 3] bone heads of the reference (A-)pose (identity deltas, root at the origin) for `motion`'s
        phenotype (anny's default subject when None), metres, anny world (z up), float64."""
        return self._reference(motion)["bone_poses"][0, :, :3, 3].detach().cpu().numpy().astype(np.float64)

    def template(self, motion: BodyMotion) -> BodyTemplate:
        o = self._reference(motion)
        return BodyTemplate(name="anny", vertices=o["rest_vertices"][0].float(), faces=self.faces(),
                            skin_weights=self.dense_skin_weights().float(), parents=self.parents,
                            joint_names=self.joint_names)

    def pose(self, motion: BodyMotion) -> PosedBody:
        o = self.run(motion)
        # M_j = bone_pose_j @ rest_bone_pose_j^-1 : canonical (rest) -> posed world (Eq. 1)
        M = o["bone_poses"] @ torch.linalg.inv(o["rest_bone_poses"])[None]
        rot = torch.as_tensor(motion.pose_parameters[:, :, :3, :3], dtype=torch.float64)
        feats = matrix_to_axis_angle(rot)
        feats[:, 0] = 0.0  # root: global heading carries no pose-dependent deformation
        return PosedBody(joint_transforms=M.float(), vertices=o["vertices"].float(), pose_features=feats.float())


    def motion_from_joint_transforms(self, motion: BodyMotion, joint_transforms: torch.Tensor) -> BodyMotion:
        """The inverse of `pose` for the pose: [frames, 104, 4, 4] joint transforms M'_j (canonical -> world, Eq. 1;
        e.g. refined by model/pose_refine.py) -> `motion` with the anny "local-ref" pose parameters whose forward
        kinematics give them (bone_pose'_j = M'_j rest_bone_pose_j, then anny's own inversion), its phenotype and
        frame index kept. Exact for rigid M'_j: anny's local deltas carry a translation, so any rigid per-bone
        motion is representable."""
        M = torch.as_tensor(joint_transforms, dtype=torch.float64, device=self.device)
        if M.ndim != 4 or M.shape[0] != motion.num_frames or M.shape[1:] != (104, 4, 4):
            raise ValueError(f"joint_transforms must be [{motion.num_frames}, 104, 4, 4], got {tuple(M.shape)}")
        rest = self._reference(motion)["rest_bone_poses"]  # [1, 104, 4, 4]
        with torch.no_grad():
            pp = self.model.get_pose_parameterization(
                {"rest_bone_poses": rest.expand(M.shape[0], -1, -1, -1), "bone_poses": M @ rest}, "local-ref")
        return replace(motion, pose_parameters=pp.float().cpu().numpy())


def identity_pose(frames: int) -> np.ndarray:
    """[frames, 104, 4, 4] identity deltas: anny's reference (A-)pose at the origin."""
    return np.broadcast_to(np.eye(4, dtype=np.float32), (frames, 104, 4, 4)).copy()
