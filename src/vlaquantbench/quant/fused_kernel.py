"""Per-token activation fake quantization fused into one GPU kernel, swapped into installed hooks.

`InputTransform` (quant.input_transform) is written as readable tensor code: a float32 copy, an absmax
reduction, a division, a rounding, a clamp, a multiplication and a cast -- seven kernels and as
many passes over the activation per linear call. Here the same arithmetic runs as one Triton
program per token (one read, one write), bit-identical to `quant.grid.fake_quant_activation`
(the correctly rounded quotient of IEEE division, round-half-even `rint`, the same 1e-8 scale
floor and dtype round trips; bit-identical on CUDA, where the benchmark checks it).

`fuse_activation_hooks(report)` replaces the transform of every counting hook of a quantization
report by `FusedInputTransform`, which also computes once the quantized input that several
layers read (q/k/v projections, gate/up projections share one input), rotated first where the
transform rotates (`InputTransform.rotation`). Hook call counting is
untouched. On a device other than CUDA it falls back to the reference transform.

`rotated_fake_quant` rotates by a `quant.hadamard.BlockHadamard` and quantizes in the same pass:
the row read once as a tile of blocks, multiplied by the +-1 Sylvester factors with `tl.dot` on the
tensor cores (float32 accumulation; float32 operands in three exact bf16 parts), rounded to the
row's dtype, quantized. It equals the reference up to the float32 rounding of R x (sums in another
order): on an H200, all but <= 7.3e-6 of the values of bf16 rows.
"""

from __future__ import annotations

import numpy as np
import torch

from vlaquantbench.quant.grid import SCALE_FLOOR
from vlaquantbench.quant.hadamard import BlockHadamard
from vlaquantbench.quant.input_transform import InputTransform

try:  # Triton ships with torch's CUDA wheels; without it (or a GPU) the reference code runs.
    import triton
    import triton.language as tl
    from triton.language.extra import libdevice
except ImportError:  # pragma: no cover - torch CPU wheels without Triton
    triton = None


if triton is not None:

    @triton.jit
    def fake_quant_scaled(x, absmax, q_max, inv_q_max, scale_floor):
        """`quant.grid.fake_quant_sym` of float32 values of one row whose absmax is `absmax`, in
        float32: for Triton kernels that reduce a row in pieces before quantizing it."""
        # torch divides a CUDA tensor by a Python scalar as a product with its float32 reciprocal.
        scale = tl.maximum(absmax, scale_floor) * inv_q_max
        # x / scale rounded as IEEE division rounds it, without a division per value: the product
        # with the row's correctly rounded reciprocal, corrected once by its exact residual
        # (Markstein: y = RN(1/b) and q within an ulp of a/b give RN(q + RN(a - bq) y) = RN(a/b)).
        # On an H200 the VLM's GELU product with its quantization took 36 instead of 41 us.
        inv_scale = tl.div_rn(1.0, scale)
        q0 = x * inv_scale
        q = libdevice.rint(tl.fma(tl.fma(-q0, scale, x), inv_scale, q0))
        return tl.minimum(tl.maximum(q, -q_max - 1.0), q_max) * scale

    @triton.jit
    def fake_quant_row(x, q_max, inv_q_max, scale_floor):
        """`quant.grid.fake_quant_sym` of one row of float32 values (padding lanes 0), in float32:
        for Triton kernels that quantize the row they compute."""
        return fake_quant_scaled(x, tl.max(tl.abs(x), axis=0), q_max, inv_q_max, scale_floor)

    @triton.jit
    def _per_token_fake_quant(
        x_ptr, y_ptr, smooth_ptr, clip_ptr, n_cols, q_max, inv_q_max, scale_floor,
        HAS_SMOOTH: tl.constexpr, HAS_CLIP: tl.constexpr, BLOCK: tl.constexpr,
    ):
        row = tl.program_id(0).to(tl.int64)
        cols = tl.arange(0, BLOCK)
        inside = cols < n_cols
        x = tl.load(x_ptr + row * n_cols + cols, mask=inside, other=0.0)
        dtype = x.dtype
        x = x.to(tl.float32)
        if HAS_SMOOTH:
            s = tl.load(smooth_ptr + cols, mask=inside, other=1.0)
            x = tl.div_rn(x, s).to(dtype).to(tl.float32)
        if HAS_CLIP:
            c = tl.load(clip_ptr + cols, mask=inside, other=1.0)
            x = tl.maximum(tl.minimum(x, c), -c).to(dtype).to(tl.float32)
        y = fake_quant_row(x, q_max, inv_q_max, scale_floor)
        tl.store(y_ptr + row * n_cols + cols, y.to(dtype), mask=inside)

    @triton.jit
    def _bfloat16_parts(a):
        """float32 `a` as the sum of three bfloat16 parts (8 significant bits each, so exact for every
        float32): their products with +-1 matrices are exact on the bf16 tensor cores, accumulated in
        float32, so a product to float32 rounding (tf32 inputs would keep 11 bits)."""
        high = a.to(tl.bfloat16)
        rest = a - high.to(tl.float32)
        middle = rest.to(tl.bfloat16)
        return high, middle, (rest - middle.to(tl.float32)).to(tl.bfloat16)

    @triton.jit
    def token_tile(first_token, n_tokens, n_tile_rows, TOKENS: tl.constexpr, TILE_ROWS: tl.constexpr,
                   INNER: tl.constexpr):
        """The tile of `TOKENS` consecutive tokens' rows from `first_token`, each as TILE_ROWS x INNER
        (row-major, its first n_tile_rows rows valid): (tile row r, column, each row's token, each
        value's offset within its token's row, valid values)."""
        rows = tl.arange(0, TOKENS * TILE_ROWS)
        token = first_token + rows // TILE_ROWS
        within_token = rows % TILE_ROWS
        cols = tl.arange(0, INNER)
        inside = ((within_token < n_tile_rows) & (token < n_tokens))[:, None]
        return rows, cols, token, within_token[:, None] * INNER + cols[None, :], inside

    @triton.jit
    def per_token(row_values, TOKENS: tl.constexpr, TILE_ROWS: tl.constexpr, IS_MAX: tl.constexpr):
        """A tile's per-row reductions (max or sum) reduced per token, as a column over the tile's rows
        (one token: a scalar, the form measured on an H200)."""
        if TOKENS == 1:
            if IS_MAX:
                values = tl.max(row_values, axis=0)
            else:
                values = tl.sum(row_values, axis=0)
        else:
            by_token = tl.reshape(row_values, (TOKENS, TILE_ROWS))
            if IS_MAX:
                token_values = tl.max(by_token, axis=1)
            else:
                token_values = tl.sum(by_token, axis=1)
            values = tl.reshape(tl.broadcast_to(token_values[:, None], (TOKENS, TILE_ROWS)), (TOKENS * TILE_ROWS,))
            values = values[:, None]
        return values

    @triton.jit
    def rotated_fake_quant_tile(x, tile_rows, inner_cols, inner_ptr, outer_ptr, inner_signs_ptr, outer_signs_ptr,
                                q_max, inv_q_max, scale_floor, OUTER: tl.constexpr, INNER: tl.constexpr,
                                TOKENS: tl.constexpr, TILE_ROWS: tl.constexpr):
        """TOKENS tokens' rows `x` (bf16 or float32; `token_tile`), each laid out as TILE_ROWS rows
        r = block * OUTER + p of INNER columns (padding rows 0): X H_q per tile row, then H_p (.) per
        block as a product with blockdiag(H_p, ...), the factors' signs read at `inner_signs_ptr`,
        `outer_signs_ptr` (`BlockHadamard.inner_signs`, `outer_signs`), each product scaled by the
        reference factor's entry (read at `inner_ptr`, `outer_ptr`); rounded to x's dtype as
        `BlockHadamard.__call__` rounds it; then quantized per token. Returns float32 values (padding
        rows 0)."""
        dtype = x.dtype
        inner = tl.load(inner_signs_ptr + inner_cols[:, None] * INNER + inner_cols[None, :])
        if dtype == tl.bfloat16:  # bf16 values times +-1 are exact products: one pass suffices
            rotated = tl.dot(x, inner)
        elif INNER <= 32:
            # float32 rows (lerobot's SigLIP tower) with small blocks (fc2's 16): fused multiply-adds.
            # With blocks of 128 the float32 factor no longer fits in registers (ptxas spills KiBs).
            rotated = tl.dot(x.to(tl.float32), inner.to(tl.float32), input_precision="ieee")
        else:
            high, middle, low = _bfloat16_parts(x.to(tl.float32))
            rotated = tl.dot(high, inner, tl.dot(middle, inner, tl.dot(low, inner)))
        rotated = rotated * tl.load(inner_ptr)  # +1/sqrt(q) in float32, as the reference factor has it
        if OUTER > 1:
            # blockdiag(H_p, H_p, ...) over the tile's rows (symmetric; a block never spans two tokens,
            # TILE_ROWS being a multiple of OUTER); padding rows stay zero
            same_block = (tile_rows[:, None] // OUTER) == (tile_rows[None, :] // OUTER)
            within = tile_rows % OUTER
            outer = tl.load(outer_signs_ptr + within[:, None] * OUTER + within[None, :], mask=same_block, other=0.0)
            high, middle, low = _bfloat16_parts(rotated)
            rotated = tl.dot(outer, high, tl.dot(outer, middle, tl.dot(outer, low))) * tl.load(outer_ptr)
        rotated = rotated.to(dtype).to(tl.float32)
        absmax = per_token(tl.max(tl.abs(rotated), axis=1), TOKENS, TILE_ROWS, True)
        return fake_quant_scaled(rotated, absmax, q_max, inv_q_max, scale_floor)

    @triton.jit
    def _rotated_fake_quant(
        x_ptr, y_ptr, inner_ptr, outer_ptr, inner_signs_ptr, outer_signs_ptr, n_tokens, n_cols, n_tile_rows, q_max,
        inv_q_max, scale_floor, OUTER: tl.constexpr, INNER: tl.constexpr, TOKENS: tl.constexpr,
        TILE_ROWS: tl.constexpr,
    ):
        """TOKENS tokens per program: their rows read once as a tile (`token_tile`), rotated and
        quantized (`rotated_fake_quant_tile`), written once."""
        first = tl.program_id(0).to(tl.int64) * TOKENS
        rows, cols, token, within, inside = token_tile(first, n_tokens, n_tile_rows, TOKENS, TILE_ROWS, INNER)
        offsets = token[:, None] * n_cols + within
        x = tl.load(x_ptr + offsets, mask=inside, other=0.0)
        y = rotated_fake_quant_tile(x, rows, cols, inner_ptr, outer_ptr, inner_signs_ptr, outer_signs_ptr,
                                    q_max, inv_q_max, scale_floor, OUTER, INNER, TOKENS, TILE_ROWS)
        tl.store(y_ptr + offsets, y.to(x.dtype), mask=inside)


def supports(x: torch.Tensor) -> bool:
    """Whether the Triton kernels run on `x`: a CUDA tensor, with Triton installed."""
    return triton is not None and x.is_cuda


def fake_quant_row_args(bits: int) -> tuple[float, float, float]:
    """`fake_quant_row`'s (q_max, inv_q_max, scale_floor) for a bit width: the float32 reciprocal
    of q_max that torch multiplies by when it divides a CUDA tensor by the Python scalar."""
    q_max = float(2 ** (bits - 1) - 1)
    return q_max, float(np.float32(1.0) / np.float32(q_max)), SCALE_FLOOR


def fused_fake_quant(x: torch.Tensor, bits: int, smooth: torch.Tensor | None = None,
                     clip: torch.Tensor | None = None) -> torch.Tensor:
    """`InputTransform(smooth, clip, bits)(x)` in one kernel (CUDA tensors only)."""
    x = x.contiguous()
    n_cols = x.shape[-1]
    y = torch.empty_like(x)
    block = triton.next_power_of_2(n_cols)
    smooth_arg = smooth.float().contiguous() if smooth is not None else x
    clip_arg = clip.float().contiguous() if clip is not None else x
    _per_token_fake_quant[(x.numel() // n_cols,)](
        x, y, smooth_arg, clip_arg, n_cols, *fake_quant_row_args(bits),
        HAS_SMOOTH=smooth is not None, HAS_CLIP=clip is not None, BLOCK=block,
        num_warps=min(16, max(1, block // 512)),
    )
    return y


def supports_rotation(rotation) -> bool:
    """Whether `rotated_fake_quant` computes `rotation`: a `BlockHadamard` of blocks of at least 16
    (tl.dot's smallest dimension); smaller blocks (demo widths only) run the reference code."""
    return triton is not None and isinstance(rotation, BlockHadamard) and rotation.inner_order >= 16


# Tile rows (tokens times each token's tile rows) up to which tokens may share a program.
MAX_SHARED_TILE_ROWS = 128


def rotation_tile(n_cols: int, rotation: BlockHadamard, n_tokens: int = 1, tokens_per_program: int = 1,
                  num_warps: int | None = None) -> dict:
    """The launch arguments of a kernel built on `rotated_fake_quant_tile` for `n_tokens` rows of
    `n_cols`: the factors' entries, the tile's valid rows and its constexpr shape, the warps, and
    `grid`, the programs. A program takes one token by default, the form measured on an H200; with
    `tokens_per_program` (a power of two, the tile at most `MAX_SHARED_TILE_ROWS` rows) several share
    one, reading the Hadamard factors once and multiplying taller tiles -- for many rows (the
    expert's 1,600 x 1,024 at batch 32 took 13 us at one token per program, against 2.5 unrotated);
    on an H200 that helped only SigLIP's float32 rows (`benchmarks/results/gpu_hadamard_captured_run4.json`,
    `rotation_kernel_us`). `num_warps` overrides the warps chosen from the tile's size."""
    blocks = n_cols // rotation.block
    outer = rotation.outer_order
    tile_rows = max(16, triton.next_power_of_2(blocks) * outer)  # tl.dot's smallest dimension is 16
    if (tokens_per_program < 1 or tokens_per_program & (tokens_per_program - 1)
            or (tokens_per_program > 1 and tokens_per_program * tile_rows > MAX_SHARED_TILE_ROWS)):
        raise ValueError(f"tokens_per_program must be a power of two with at most {MAX_SHARED_TILE_ROWS} tile rows "
                         f"({tile_rows} per token of {n_cols}), not {tokens_per_program}")
    # The factors' entries are read on the device (no host sync, so it runs inside a graph capture).
    return {"inner_ptr": rotation.inner, "outer_ptr": rotation.outer if rotation.outer is not None else rotation.inner,
            "inner_signs_ptr": rotation.inner_signs, "outer_signs_ptr": rotation.outer_signs,
            "n_tokens": n_tokens, "n_tile_rows": blocks * outer, "OUTER": outer, "INNER": rotation.inner_order,
            "TOKENS": tokens_per_program, "TILE_ROWS": tile_rows, "grid": (triton.cdiv(n_tokens, tokens_per_program),),
            "num_warps": num_warps or min(8, max(4, tokens_per_program * tile_rows * rotation.inner_order // 1024))}


def rotated_fake_quant(x: torch.Tensor, rotation: BlockHadamard, bits: int, *,
                       num_warps: int | None = None, tokens_per_program: int = 1) -> torch.Tensor:
    """`InputTransform(rotation=rotation, act_bits=bits)(x)` in one kernel (a CUDA tensor, or a CPU
    one under Triton's interpreter; `supports_rotation(rotation)`): R x, rounded to x's dtype, then
    quantized per token. Equal to the reference to float32 rounding of R x (both sum the same
    products in float32, in different orders): a value differs only where that moves R x across a
    rounding boundary of x's dtype. `num_warps` overrides `rotation_tile`'s choice;
    `tokens_per_program` as there."""
    x = x.contiguous()
    n_cols = x.shape[-1]
    y = torch.empty_like(x)
    q_max, inv_q_max, scale_floor = fake_quant_row_args(bits)
    launch = rotation_tile(n_cols, rotation, x.numel() // n_cols, tokens_per_program, num_warps)
    _rotated_fake_quant[launch.pop("grid")](x, y, n_cols=n_cols, q_max=q_max, inv_q_max=inv_q_max,
                                            scale_floor=scale_floor, **launch)
    return y


class _SharedInputs:
    """Remembers the last quantized input so that layers reading the same tensor share one kernel."""

    def __init__(self):
        self.source: torch.Tensor | None = None
        self.version = -1
        self.key = None
        self.result: torch.Tensor | None = None

    def lookup(self, x: torch.Tensor, key):
        if x is self.source and x._version == self.version and key == self.key:
            return self.result
        return None

    def store(self, x: torch.Tensor, key, result: torch.Tensor) -> None:
        self.source, self.version, self.key, self.result = x, x._version, key, result


class FusedInputTransform:
    """Same contract and result as the `InputTransform` it wraps, computed by `fused_fake_quant`."""

    def __init__(self, reference: InputTransform, shared: _SharedInputs):
        self.reference = reference
        self.shared = shared

    def __getattr__(self, name):  # smooth, clip, act_bits, is_identity as the reference has them
        return getattr(self.reference, name)

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        ref = self.reference
        if not supports(x) or ref.act_bits is None:
            return ref(x)
        # Smoothing vectors are per layer, so only plain quantization (after a rotation, which is
        # one per width) can be shared between layers.
        key = (ref.rotation, ref.act_bits) if ref.smooth is None and ref.clip is None else None
        if key is not None and (hit := self.shared.lookup(x, key)) is not None:
            return hit
        if ref.rotation is not None and key is not None and supports_rotation(ref.rotation):
            y = rotated_fake_quant(x, ref.rotation, ref.act_bits)
        else:
            rotated = x if ref.rotation is None else ref.rotation(x)
            y = fused_fake_quant(rotated, ref.act_bits, ref.smooth, ref.clip)
        if key is not None:
            self.shared.store(x, key, y)
        return y


def fuse_activation_hooks(report) -> int:
    """Swap the transforms of `report`'s counting hooks for fused ones; returns how many."""
    shared = _SharedInputs()
    for hook in report.result.hooks.values():
        if not isinstance(hook.transform, FusedInputTransform):
            hook.transform = FusedInputTransform(hook.transform, shared)
    return len(report.result.hooks)
