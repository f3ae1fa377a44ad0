"""Faster inference paths that compute the same actions as the eager policy (captured graphs,
fused activation quantization)."""

from vlaquantbench.accel.captured import CapturedSampler
from vlaquantbench.accel.fused_quant import fuse_activation_hooks

__all__ = ["CapturedSampler", "fuse_activation_hooks"]
