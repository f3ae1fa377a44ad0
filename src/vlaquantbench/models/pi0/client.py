"""pi0's LIBERO client conventions: those of pi0.5 (the same lerobot LIBERO evaluation)."""

from vlaquantbench.models.pi05.client import CLIENT, STEP_LIMITS

__all__ = ["CLIENT", "STEP_LIMITS"]
