"""The block Hadamard rotation x -> R x that `quant.transforms.Hadamard` folds into weights and
applies to inputs, and that `quant.rotation` rotates residual streams by; its own module so that the
fused kernel (`quant.fused_kernel`), the transforms and the stream rotation all read it without
importing one another."""

from __future__ import annotations

import functools
import math

import scipy.linalg
import torch

# The largest Hadamard factor a rotation multiplies by (`BlockHadamard`): blocks beyond it are
# Kronecker products of factors of at most this order, so R x costs two small products, not one b x b.
FACTOR_ORDER = 128


class BlockHadamard:
    """x -> R x for inputs of `width` channels (rows of x as vectors: x R^T), computed in float32.

    Sylvester's construction makes H_(pq) = H_p (x) H_q (Kronecker product) for powers of two p, q,
    so a block of b = p q channels, read as a p x q matrix X (row-major), rotates to H_p X H_q: two
    products with factors of order at most `FACTOR_ORDER`, O(b (p + q)) per block instead of O(b^2)
    (pi0.5's VLM down_proj input, 16,384 wide, is one block: 128 + 128 instead of 16,384 multiply-adds
    per value, and no 1 GiB matrix). Equal to the dense blockdiag(H_b / sqrt(b)) up to rounding.

    Equal (and hashed) by block and device: layers of one width share one rotation, so the fast
    path rotates an input that several layers read (q/k/v, gate/up) once (`quant.hooks.Rotated`)."""

    def __init__(self, width: int, device: torch.device | str = "cpu"):
        self.block = width & -width  # the largest power of two dividing the width
        self.inner_order = min(self.block, FACTOR_ORDER)
        self.outer_order = self.block // self.inner_order
        self.inner = _orthonormal_hadamard(self.inner_order, device)
        self.outer = _orthonormal_hadamard(self.outer_order, device) if self.outer_order > 1 else None
        # The factors' +-1 entries, exact in bfloat16, for the Triton kernels to read rather than
        # derive: deriving a 128 x 128 factor took seven integer passes over it in every program.
        self.inner_signs = _hadamard_signs(self.inner_order, device)
        self.outer_signs = _hadamard_signs(self.outer_order, device)

    @property
    def name(self) -> str:
        return f"hadamard{self.block}"

    def rotate(self, x: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
        """Every row of x (last dimension) times R^T, computed in `dtype`; also folds R^T into a weight."""
        blocks = x.to(dtype).reshape(*x.shape[:-1], -1, self.outer_order, self.inner_order)
        rotated = blocks @ self.inner.to(dtype)  # X H_q (the factors are symmetric)
        if self.outer is not None:
            rotated = self.outer.to(dtype) @ rotated  # H_p (X H_q)
        return rotated.reshape(x.shape)

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        return self.rotate(x, torch.float32).to(x.dtype)

    def map_hessian(self, hessian: torch.Tensor) -> torch.Tensor:
        """R (X^T X) R^T, the second moment of the rotated inputs, in the Hessian's dtype."""
        return self.rotate(self.rotate(hessian, hessian.dtype).t(), hessian.dtype).t()

    @property
    def is_identity(self) -> bool:
        return False

    def __eq__(self, other) -> bool:
        return (isinstance(other, BlockHadamard) and other.block == self.block
                and other.inner.device == self.inner.device)

    def __hash__(self) -> int:
        return hash((BlockHadamard, self.block, str(self.inner.device)))


# One read-only copy per order and device, whatever the number of layers rotated (456 for pi0.5's e2e).
@functools.cache
def _hadamard_signs(order: int, device: torch.device | str) -> torch.Tensor:
    """Sylvester's +-1 Hadamard matrix of `order` (a power of two), bfloat16."""
    return torch.tensor(scipy.linalg.hadamard(order), dtype=torch.bfloat16, device=device)


@functools.cache
def _orthonormal_hadamard(order: int, device: torch.device | str) -> torch.Tensor:
    """Sylvester's Hadamard matrix of `order` (a power of two) scaled by 1/sqrt(order), float32."""
    return _hadamard_signs(order, device).float() / math.sqrt(order)
