"""Synthetic ground-truth capture: an anny body in a simulated skirt, rendered through calibrated, distorted
cameras into an EasyMocap-layout capture (`synthesize(out, SynthConfig.preset("tiny", seed))`)."""

from avatarctl.synth.capture import SynthResult, synthesize
from avatarctl.synth.config import PRESETS, SynthConfig

__all__ = ["PRESETS", "SynthConfig", "SynthResult", "synthesize"]
