"""The Triton GEMMs of the real-kernel methods (`quant.kernels.scaled_gemm`) under Triton's interpreter on the
CPU: int8 products equal `torch._int_mm`'s sums rescaled as `dequantize_int32` does, with and without the inner
dimension split; the int4 product equals x times the dequantized weights, including inputs that are not a
multiple of the packing block and a last split that is short; the packing puts each input where the kernel reads
it; the tiles `tile_for` picks launch the GPU's worth of programs; and every kernel compiles for Hopper (sm_90),
wgmma where the tile has 64 rows or more. On a GPU the same kernels ran against cuBLAS and tinygemm
(benchmarks/gpu_kernel_shapes.py, benchmarks/results/gpu_kernel_checks.json)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import pytest
import torch

triton = pytest.importorskip("triton")


# Run with TRITON_INTERPRET=1 set before Triton is imported (hence a subprocess): each case prints what the test
# compares. The interpreter multiplies no bfloat16 tiles correctly, so the int4 kernel runs on float32 operands there
# (`w4a16_gemm` chooses them for CPU tensors); the int8 products are exact in both.
SCRIPT = textwrap.dedent("""
    import json, torch
    from vlaquantbench.quant.kernels import scaled_gemm as sg
    from vlaquantbench.quant.kernels.int8 import INT_MM_MIN_ROWS, dequantize_int32
    g = torch.Generator().manual_seed(0)
    out = {"int8": [], "w4a16": []}
    for m, k, n in ((50, 1024, 96), (7, 1152, 64), (33, 4304, 32)):
        a = torch.randint(-127, 128, (m, k), dtype=torch.int8, generator=g)
        w = torch.randint(-127, 128, (n, k), dtype=torch.int8, generator=g)
        sa, sb = torch.rand(m, 1, generator=g) * 0.01, torch.rand(1, n, generator=g) * 0.01
        padded = torch.nn.functional.pad(a, (0, 0, 0, max(INT_MM_MIN_ROWS, -(-m // 8) * 8) - m))
        expected = dequantize_int32(torch._int_mm(padded, w.t())[:m], sa, sb, torch.float32)
        for tile in (sg.Tile(16, 32, 128), sg.Tile(16, 32, 128, split=4), sg.Tile(32, 64, 256, split=3)):
            got = sg.scaled_gemm(a, w.t(), sa, sb, torch.float32, tile)
            out["int8"].append([m, k, n, tile.describe(), bool(torch.equal(got, expected))])
    # (3, 1100, 32, 1152) split 4: 320 inputs a split, the last one 192.
    for m, k, n, k_packed in ((5, 200, 64, 256), (50, 300, 96, 384), (3, 1100, 32, 1152)):
        q = torch.randint(0, 16, (n, k_packed), generator=g)
        scales = (torch.rand(k_packed // 128, n, generator=g) * 0.1).bfloat16()
        zeros = (torch.randn(k_packed // 128, n, generator=g) * 0.1).bfloat16()
        x = torch.randn(m, k, generator=g)
        per_input = lambda t: t.float().repeat_interleave(128, 0).t()
        expected = x @ ((q.float() - 8) * per_input(scales) + per_input(zeros))[:, :k].t()
        for tile in (sg.Tile(16, 32, 64), sg.Tile(16, 32, 128, split=2), sg.Tile(16, 64, 64, split=4)):
            got = sg.w4a16_gemm(x, sg.pack_int4(q), scales, zeros, 128, torch.float32, tile)
            error = ((got - expected).abs().max() / expected.abs().max()).item()
            out["w4a16"].append([m, k, n, tile.describe(), error])
    try:
        sg.w4a16_gemm(x, sg.pack_int4(q), scales, zeros, 128, torch.float32, sg.Tile(16, 32, 32))
    except ValueError as error:
        out["refused"] = str(error)
    print(json.dumps(out))
""")


@pytest.fixture(scope="module")
def interpreted() -> dict:
    done = subprocess.run([sys.executable, "-c", SCRIPT], env={**os.environ, "TRITON_INTERPRET": "1"},
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_int8_scaled_gemm_equals_int_mm_rescaled_in_any_tile_and_split(interpreted):
    assert len(interpreted["int8"]) == 9
    for m, k, n, tile, equal in interpreted["int8"]:
        assert equal, (m, k, n, tile)


def test_w4a16_gemm_is_x_times_the_dequantized_weights(interpreted):
    assert len(interpreted["w4a16"]) == 9
    for m, k, n, tile, error in interpreted["w4a16"]:
        assert error < 1e-5, (m, k, n, tile, error)
    assert "do not fit" in interpreted["refused"]  # a K step of 32 is no multiple of the packing block


def test_pack_int4_puts_input_i_and_i_plus_half_a_block_in_one_byte():
    from vlaquantbench.quant.kernels.scaled_gemm import PACK, pack_int4

    q = torch.randint(0, 16, (6, 3 * PACK), generator=torch.Generator().manual_seed(2))
    packed = pack_int4(q)
    assert packed.shape == (3 * PACK // 2, 6) and packed.dtype == torch.uint8
    for block in range(3):
        for i in range(PACK // 2):
            row = packed[block * PACK // 2 + i]
            assert torch.equal(row & 15, q[:, block * PACK + i].to(torch.uint8))
            assert torch.equal(row >> 4, q[:, block * PACK + PACK // 2 + i].to(torch.uint8))


def test_tile_for_fills_the_gpu_for_few_rows_and_fits_each_kernel():
    from vlaquantbench.quant.kernels.scaled_gemm import PACK, SMS, tile_for

    # pi0.5's products at batch 1 and 8 (rows x inputs x outputs): expert, vision tower, language model.
    shapes = [(50, 1024, 2560), (50, 1024, 8192), (50, 2048, 1024), (50, 4096, 1024), (512, 1152, 4304),
              (712, 2048, 32768), (712, 16384, 2048), (400, 4096, 1024), (5696, 2048, 2560)]
    for kind in ("int8", "fp8", "w4a16"):
        for m, k, n in shapes:
            tile = tile_for(kind, m, k, n)
            programs = -(-m // tile.m) * -(-n // tile.n) * tile.split
            if m <= 64:
                assert tile.m == 16 and (programs * 2 > SMS or k // (tile.split * 2) < 2 * tile.k), (kind, m, k, n)
            else:
                assert tile.split == 1
            if kind == "w4a16":
                assert tile.k % PACK == 0 and 128 % tile.k == 0
    assert tile_for("int8", 50, 4096, 1024).split == 2  # 64 programs of 16 x 64: two splits fill 128 of 132 SMs


@pytest.mark.parametrize("kernel", ["int8", "fp8", "sum_parts", "w4a16"])
def test_gemm_kernels_compile_for_hopper(kernel):
    """No GPU here, but Triton's compiler runs: every kernel compiles to sm_90 PTX, with wgmma (Hopper's
    warpgroup MMA) for 128-row tiles and mma.sync for 16-row ones."""
    from triton.backends.compiler import GPUTarget
    from triton.compiler import ASTSource

    from vlaquantbench.quant.kernels import scaled_gemm as sg

    def ptx(fn, signature, constexprs, warps):
        source = ASTSource(fn=fn, signature=signature | {name: "constexpr" for name in constexprs}, constexprs=constexprs)
        return triton.compile(source, target=GPUTarget("cuda", 90, 32), options={"num_warps": warps}).asm["ptx"]

    ints = dict.fromkeys(("M", "N", "K", "K_SPLIT"), "i32")
    if kernel == "sum_parts":
        code = ptx(sg._sum_parts, {"part_ptr": "*i32", "sa_ptr": "*fp32", "sb_ptr": "*fp32", "c_ptr": "*bf16",
                                   "M": "i32", "N": "i32"}, {"SPLIT": 4, "SCALED": True, "BLOCK": 1024}, 4)
        assert ".target sm_90" in code
        return
    for rows, warps, split in ((16, 4, 4), (128, 8, 1)):
        if kernel == "w4a16":
            signature = {"x_ptr": "*bf16", "w_ptr": "*u8", "s_ptr": "*bf16", "z_ptr": "*bf16", "c_ptr": "*bf16",
                         "part_ptr": "*fp32", **ints, "K_PACKED": "i32", "stride_xm": "i32", "stride_cm": "i32"}
            constexprs = {"GROUP": 128, "BLOCK_M": rows, "BLOCK_N": 128, "BLOCK_K": 64, "GROUP_M": 8, "SPLIT": split,
                          "PACK": sg.PACK, "OPERAND": triton.language.bfloat16}
            code = ptx(sg._w4a16_gemm, signature, constexprs, warps)
        else:
            element = "i8" if kernel == "int8" else "fp8e4nv"
            signature = {"a_ptr": f"*{element}", "b_ptr": f"*{element}", "sa_ptr": "*fp32", "sb_ptr": "*fp32",
                         "c_ptr": "*bf16", "part_ptr": "*i32" if kernel == "int8" else "*fp32", **ints,
                         **dict.fromkeys(("stride_am", "stride_ak", "stride_bk", "stride_bn", "stride_cm"), "i32")}
            constexprs = {"INT_ACC": kernel == "int8", "BLOCK_M": rows, "BLOCK_N": 128, "BLOCK_K": 128, "GROUP_M": 8,
                          "SPLIT": split}
            code = ptx(sg._scaled_gemm, signature, constexprs, warps)
        assert ".target sm_90" in code
        assert ("wgmma" in code) == (rows == 128), (kernel, rows)
