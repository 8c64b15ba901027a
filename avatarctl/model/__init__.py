"""The SLRF core model: config, node deformer, per-node cVAEs, local fields, heads, losses, avatar.

Independent of file formats: never imports `avatarctl.io`, `avatarctl.cli` or `avatarctl.project`.
"""

from avatarctl.model.avatar import FrameConditioning, NodeState, RenderOutputs, SlrfAvatar
from avatarctl.model.config import ModelConfig
from avatarctl.model.losses import LossTerms

__all__ = ["FrameConditioning", "LossTerms", "ModelConfig", "NodeState", "RenderOutputs", "SlrfAvatar"]
