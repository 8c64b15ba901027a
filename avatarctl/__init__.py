"""avatarctl: animatable clothed human avatars from calibrated RGB video.

Implements *Structured Local Radiance Fields for Human Avatar Modeling* (Zheng et al., CVPR 2022).
Importing this package has no side effects and does not import torch.
"""

__version__ = "0.1.0"
