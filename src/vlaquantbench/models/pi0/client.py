"""pi0's LIBERO client conventions: those of pi0.5 (the same lerobot LIBERO evaluation)."""

from vlaquantbench.models.pi05.client import CLIENT

__all__ = ["CLIENT"]
