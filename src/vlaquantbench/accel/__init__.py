"""Faster inference paths that compute the same actions as the eager policy (captured graphs,
fused activation quantization)."""

from vlaquantbench.accel.captured import CapturedSampler

__all__ = ["CapturedSampler"]
