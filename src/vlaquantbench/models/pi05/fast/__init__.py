"""Fast pi0.5 inference that computes the eager policy's actions: the chunk as one CUDA graph
(`captured`) over a capture-ready rewrite of lerobot's `sample_actions` (`static_sampling`), whose
linears sharing an input run as one product (`linear_groups`)."""

from vlaquantbench.models.pi05.fast.captured import CapturedSampler

__all__ = ["CapturedSampler"]
