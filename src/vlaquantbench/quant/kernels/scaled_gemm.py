"""Triton GEMMs for packed weights, with the launch tile a parameter (`Tile`, chosen by `tile_for`):
- `scaled_gemm`, W8A8: y = (A @ B) * s_a * s_b, A's rows quantized per token (int8 or FP8 e4m3), B a packed
  weight's transpose, the scales applied to the accumulator in float32 and the result rounded once to the output
  dtype;
- `w4a16_gemm`, int4 weights in groups along the input with a scale and a zero each, dequantized to bf16 inside
  the kernel and multiplied with bf16 inputs: y = x @ ((q - 8) * scale + zero)^T.

Why not only the libraries: cuBLASLt's int8 product (`torch._int_mm`) takes at least 17 rows and leaves its int32
sums for a second kernel to rescale; `torch._scaled_mm` chooses 128 x 128 tiles for pi0.5's action expert, whose
products have 50 rows, 720 of them a chunk; tinygemm (`torch._weight_int4pack_mm`) is a kernel for a few rows: at
pi0.5's 50 to 712 rows it ran 3 to 23 times slower than bf16 on an H100 (benchmarks/results/gpu_kernel_shapes*.json).
Here the tile is a parameter, so a product of few rows runs on a small one, the rescale is the GEMM's epilogue, and a
product with too few output tiles to fill the GPU splits its inner dimension (`Tile.split`): each split's partial
sums go to a float32 (int32 for int8) buffer, which a second kernel adds up in split order, so the result does not
depend on timing.

int8 accumulates in int32 (exact, in any order) and rescales as `(acc * s_a) * s_b` in float32, the arithmetic of
`int8.dequantize_int32`: equal results. FP8 accumulates in float32 on the tensor cores; with 64 rows or more a tile
uses Hopper's wgmma, whose FP8 accumulation is the fast kind (as `torch._scaled_mm(use_fast_accum=True)`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

try:
    import triton
    import triton.language as tl
except ImportError:  # pragma: no cover
    triton = None

PACK = 64  # w4a16's packing block along the input: byte row i of a block holds inputs i and i + PACK / 2


@dataclass(frozen=True)
class Tile:
    """One launch configuration: the block of the output a program computes, its K step, pipeline
    stages and warps, and how many parts the inner dimension is split into."""

    m: int
    n: int
    k: int
    stages: int = 3
    warps: int = 4
    split: int = 1

    def describe(self) -> str:
        return f"{self.m}x{self.n}x{self.k}/s{self.stages}w{self.warps}" + (f"k{self.split}" if self.split > 1 else "")


# Measured choices by (kind, rows, inner, outer), set by a benchmark that sweeps tiles; `tile_for` reads them first.
MEASURED_TILES: dict[tuple[str, int, int, int], Tile] = {}
SMS = 132  # an H100's or H200's multiprocessors: the programs a product should at least launch


def tile_for(kind: str, m: int, k: int, n: int) -> Tile:
    """The tile for an (m x k) @ (k x n) product of `kind` ('int8', 'fp8' or 'w4a16'): a measured one if
    `MEASURED_TILES` holds it, else by size: 128 x 128 with 8 warps for thousands of rows; for a few rows a row
    block of 16 and the inner dimension split until the programs fill the GPU."""
    measured = MEASURED_TILES.get((kind, m, k, n))
    if measured is not None:
        return measured
    step = 64 if kind == "w4a16" else 128
    if m > 1024 or n >= 16384:
        return Tile(128, 128, step, 3, 8)
    if m > 64:
        return Tile(64, 128, step) if n >= 2560 else Tile(64, 64, step)
    tile_n = 64
    programs = -(-m // 16) * -(-n // tile_n)
    split = 1
    while programs * split * 2 <= SMS and k // (split * 2) >= 2 * step:
        split *= 2
    return Tile(16, tile_n, step, 4, 4, split)


if triton is not None:

    @triton.jit
    def _program_block(M, N, BLOCK_M: tl.constexpr, BLOCK_N: tl.constexpr, GROUP_M: tl.constexpr):
        """(row block, column block) of program axis 0, programs that share B's columns together (L2 reuse)."""
        pid = tl.program_id(0)
        grid_m = tl.cdiv(M, BLOCK_M)
        grid_n = tl.cdiv(N, BLOCK_N)
        width = GROUP_M * grid_n
        first_m = (pid // width) * GROUP_M
        size_m = tl.minimum(grid_m - first_m, GROUP_M)
        return first_m + (pid % width) % size_m, (pid % width) // size_m

    @triton.jit
    def _scaled_gemm(a_ptr, b_ptr, sa_ptr, sb_ptr, c_ptr, part_ptr, M, N, K, K_SPLIT, stride_am, stride_ak,
                     stride_bk, stride_bn, stride_cm, INT_ACC: tl.constexpr, BLOCK_M: tl.constexpr,
                     BLOCK_N: tl.constexpr, BLOCK_K: tl.constexpr, GROUP_M: tl.constexpr, SPLIT: tl.constexpr):
        ACC: tl.constexpr = tl.int32 if INT_ACC else tl.float32
        ZERO: tl.constexpr = 0 if INT_ACC else 0.0  # an int does not cast to FP8 (other=)
        pid_m, pid_n = _program_block(M, N, BLOCK_M, BLOCK_N, GROUP_M)
        part = tl.program_id(1)
        rows = pid_m * BLOCK_M + tl.arange(0, BLOCK_M)
        cols = pid_n * BLOCK_N + tl.arange(0, BLOCK_N)
        first = part * K_SPLIT  # this split's inner range: [first, first + K_SPLIT) within K
        ks = first + tl.arange(0, BLOCK_K)
        end = tl.minimum(first + K_SPLIT, K)
        a_ptrs = a_ptr + rows[:, None].to(tl.int64) * stride_am + ks[None, :] * stride_ak
        b_ptrs = b_ptr + ks[:, None] * stride_bk + cols[None, :].to(tl.int64) * stride_bn
        acc = tl.zeros((BLOCK_M, BLOCK_N), dtype=ACC)
        for k in range(0, tl.cdiv(K_SPLIT, BLOCK_K)):
            inside = ks + k * BLOCK_K < end
            a = tl.load(a_ptrs, mask=(rows[:, None] < M) & inside[None, :], other=ZERO)
            b = tl.load(b_ptrs, mask=inside[:, None] & (cols[None, :] < N), other=ZERO)
            acc = tl.dot(a, b, acc, out_dtype=ACC)
            a_ptrs += BLOCK_K * stride_ak
            b_ptrs += BLOCK_K * stride_bk
        mask = (rows[:, None] < M) & (cols[None, :] < N)
        if SPLIT > 1:
            tl.store(part_ptr + (part * M + rows[:, None].to(tl.int64)) * N + cols[None, :], acc, mask=mask)
        else:
            sa = tl.load(sa_ptr + rows, mask=rows < M, other=0.0)
            sb = tl.load(sb_ptr + cols, mask=cols < N, other=0.0)
            y = (acc.to(tl.float32) * sa[:, None]) * sb[None, :]
            tl.store(c_ptr + rows[:, None].to(tl.int64) * stride_cm + cols[None, :], y.to(c_ptr.dtype.element_ty),
                     mask=mask)

    @triton.jit
    def _sum_parts(part_ptr, sa_ptr, sb_ptr, c_ptr, M, N, SPLIT: tl.constexpr, SCALED: tl.constexpr,
                   BLOCK: tl.constexpr):
        """c = sum of the SPLIT partial products in split order (then scaled by rows and columns)."""
        row = tl.program_id(0).to(tl.int64)
        cols = tl.program_id(1) * BLOCK + tl.arange(0, BLOCK)
        inside = cols < N
        acc = tl.load(part_ptr + row * N + cols, mask=inside, other=0)
        for part in tl.static_range(1, SPLIT):
            acc += tl.load(part_ptr + (part * M + row) * N + cols, mask=inside, other=0)
        y = acc.to(tl.float32)
        if SCALED:
            y = (y * tl.load(sa_ptr + row)) * tl.load(sb_ptr + cols, mask=inside, other=0.0)
        tl.store(c_ptr + row * N + cols, y.to(c_ptr.dtype.element_ty), mask=inside)

    @triton.jit
    def _w4a16_gemm(x_ptr, w_ptr, s_ptr, z_ptr, c_ptr, part_ptr, M, N, K, K_PACKED, K_SPLIT, stride_xm, stride_cm,
                    GROUP: tl.constexpr, BLOCK_M: tl.constexpr, BLOCK_N: tl.constexpr, BLOCK_K: tl.constexpr,
                    GROUP_M: tl.constexpr, SPLIT: tl.constexpr, PACK: tl.constexpr, OPERAND: tl.constexpr):
        HALF: tl.constexpr = BLOCK_K // 2
        SUB: tl.constexpr = PACK // 2
        pid_m, pid_n = _program_block(M, N, BLOCK_M, BLOCK_N, GROUP_M)
        part = tl.program_id(1)
        rows = pid_m * BLOCK_M + tl.arange(0, BLOCK_M)
        cols = pid_n * BLOCK_N + tl.arange(0, BLOCK_N)
        # Byte row r of a K step holds the inputs `low[r]` (low nibble) and `low[r] + SUB` (high nibble).
        r = tl.arange(0, HALF)
        low = (r // SUB) * PACK + r % SUB
        first = part * K_SPLIT
        acc = tl.zeros((BLOCK_M, BLOCK_N), dtype=tl.float32)
        for k in range(0, tl.minimum(K_SPLIT, K_PACKED - first) // BLOCK_K):  # the last split may be short
            k0 = first + k * BLOCK_K
            packed = tl.load(w_ptr + (k0 // 2 + r[:, None]).to(tl.int64) * N + cols[None, :], mask=cols[None, :] < N,
                             other=0)
            g = k0 // GROUP
            scale = tl.load(s_ptr + g * N + cols, mask=cols < N, other=0.0).to(tl.float32)[None, :]
            zero = tl.load(z_ptr + g * N + cols, mask=cols < N, other=0.0).to(tl.float32)[None, :]
            w_low = (((packed & 15).to(tl.float32) - 8.0) * scale + zero).to(OPERAND)
            w_high = (((packed >> 4).to(tl.float32) - 8.0) * scale + zero).to(OPERAND)
            x_rows = x_ptr + rows[:, None].to(tl.int64) * stride_xm
            row_ok = rows[:, None] < M
            x_low = tl.load(x_rows + (k0 + low)[None, :], mask=row_ok & (k0 + low < K)[None, :], other=0.0)
            x_high = tl.load(x_rows + (k0 + low + SUB)[None, :], mask=row_ok & (k0 + low + SUB < K)[None, :], other=0.0)
            acc = tl.dot(x_low.to(OPERAND), w_low, acc)
            acc = tl.dot(x_high.to(OPERAND), w_high, acc)
        mask = (rows[:, None] < M) & (cols[None, :] < N)
        if SPLIT > 1:
            tl.store(part_ptr + (part * M + rows[:, None].to(tl.int64)) * N + cols[None, :], acc, mask=mask)
        else:
            tl.store(c_ptr + rows[:, None].to(tl.int64) * stride_cm + cols[None, :], acc.to(c_ptr.dtype.element_ty),
                     mask=mask)


def _split_range(k: int, tile: Tile, multiple: int) -> int:
    """Inputs per split: K divided into `tile.split` parts, each a multiple of `multiple`."""
    per = -(-k // tile.split)
    return -(-per // multiple) * multiple


def _finish(parts: torch.Tensor | None, out: torch.Tensor, scale_a, scale_b, tile: Tile) -> torch.Tensor:
    if parts is not None:
        m, n = out.shape
        _sum_parts[(m, triton.cdiv(n, 1024))](parts, scale_a, scale_b, out, m, n, SPLIT=tile.split,
                                              SCALED=scale_a is not None, BLOCK=1024)
    return out


def scaled_gemm(a: torch.Tensor, b: torch.Tensor, scale_a: torch.Tensor, scale_b: torch.Tensor,
                out_dtype: torch.dtype, tile: Tile) -> torch.Tensor:
    """(a @ b) * scale_a * scale_b rounded to `out_dtype`: `a` (M x K, int8 or float8_e4m3fn), `b` (K x N, the
    same dtype, any strides), `scale_a` M float32 values (a column), `scale_b` N float32 values (a row)."""
    if triton is None:  # pragma: no cover
        raise RuntimeError("scaled_gemm needs Triton")
    (m, k), (k2, n) = a.shape, b.shape
    if k != k2 or a.dtype != b.dtype:
        raise ValueError(f"scaled_gemm: a {tuple(a.shape)} {a.dtype} and b {tuple(b.shape)} {b.dtype} do not multiply")
    if scale_a.numel() != m or scale_b.numel() != n:
        raise ValueError(f"scaled_gemm: {scale_a.numel()} row scales for {m} rows, {scale_b.numel()} column scales "
                         f"for {n} columns")
    scale_a, scale_b = scale_a.reshape(-1).float().contiguous(), scale_b.reshape(-1).float().contiguous()
    out = torch.empty(m, n, dtype=out_dtype, device=a.device)
    integer = a.dtype == torch.int8
    parts = (torch.empty(tile.split, m, n, dtype=torch.int32 if integer else torch.float32, device=a.device)
             if tile.split > 1 else None)
    grid = (triton.cdiv(m, tile.m) * triton.cdiv(n, tile.n), tile.split)
    _scaled_gemm[grid](a, b, scale_a, scale_b, out, parts if parts is not None else out, m, n, k,
                       _split_range(k, tile, tile.k), a.stride(0), a.stride(1), b.stride(0), b.stride(1),
                       out.stride(0), INT_ACC=integer, BLOCK_M=tile.m, BLOCK_N=tile.n, BLOCK_K=tile.k, GROUP_M=8,
                       SPLIT=tile.split, num_stages=tile.stages, num_warps=tile.warps)
    return _finish(parts, out, scale_a, scale_b, tile)


def pack_int4(q: torch.Tensor) -> torch.Tensor:
    """Levels `q` (out x in, integers 0..15, `in` a multiple of `PACK`) packed for `w4a16_gemm`: in/2 x out bytes,
    N-contiguous; in each block of `PACK` inputs, byte row i holds input i in its low nibble and input
    i + PACK/2 in its high one."""
    out_features, in_features = q.shape
    blocks = q.to(torch.uint8).t().reshape(in_features // PACK, 2, PACK // 2, out_features)
    return (blocks[:, 0] | (blocks[:, 1] << 4)).reshape(in_features // 2, out_features).contiguous()


def w4a16_gemm(x: torch.Tensor, packed: torch.Tensor, scales: torch.Tensor, zeros: torch.Tensor, group: int,
               out_dtype: torch.dtype, tile: Tile) -> torch.Tensor:
    """x (M x K, any float dtype, rounded to bf16) @ W^T with W[n, k] = (q - 8) * scales[k // group, n] +
    zeros[k // group, n] rounded to bf16, q from `packed` (`pack_int4`: K_packed/2 x N, K_packed a multiple of
    `group` and at least K); float32 accumulation, the result in `out_dtype`. `tile.k` must be a multiple of
    `PACK` and divide `group`.
    Under Triton's interpreter (CPU tensors) the operands stay float32: it multiplies no bf16 tiles correctly."""
    if triton is None:  # pragma: no cover
        raise RuntimeError("w4a16_gemm needs Triton")
    m, k = x.shape
    k_packed, n = 2 * packed.shape[0], packed.shape[1]
    if k > k_packed or k_packed % group or group % tile.k or tile.k % PACK or scales.shape != (k_packed // group, n):
        raise ValueError(f"w4a16_gemm: x {tuple(x.shape)}, packed {tuple(packed.shape)}, scales {tuple(scales.shape)}, "
                         f"group {group}, tile {tile.describe()} do not fit")
    x = x if x.stride(1) == 1 else x.contiguous()
    out = torch.empty(m, n, dtype=out_dtype, device=x.device)
    parts = torch.empty(tile.split, m, n, dtype=torch.float32, device=x.device) if tile.split > 1 else None
    grid = (triton.cdiv(m, tile.m) * triton.cdiv(n, tile.n), tile.split)
    _w4a16_gemm[grid](x, packed, scales, zeros, out, parts if parts is not None else out, m, n, k, k_packed,
                      _split_range(k_packed, tile, tile.k), x.stride(0), out.stride(0), GROUP=group, BLOCK_M=tile.m,
                      BLOCK_N=tile.n, BLOCK_K=tile.k, GROUP_M=8, SPLIT=tile.split, PACK=PACK,
                      OPERAND=tl.bfloat16 if x.is_cuda else tl.float32, num_stages=tile.stages, num_warps=tile.warps)
    return _finish(parts, out, None, None, tile)
