"""`quant.fused_kernel.rotated_fake_quant`, the Triton kernel that rotates by a `BlockHadamard` and
quantizes per token in one pass, run on the CPU under Triton's interpreter (`TRITON_INTERPRET=1`,
set before Triton is imported, hence a subprocess) against the reference `InputTransform`.

The interpreter of Triton 3.6 differs from the GPU where the kernels rely on it; the script
corrects the interpreter (not the kernels) so that it computes what the GPU computes:
- `tl.dot` of bfloat16 operands multiplies their bit patterns as integers (it stores bfloat16 as
  uint16): the operands are widened to float32 first, as the tensor cores read them;
- `tl.fma` rounds the product before adding: it is computed in float64 (the product of two float32
  is exact there) and rounded once;
- a float32 -> bfloat16 cast truncates: it rounds to nearest, ties to even, as the GPU's does;
- libdevice is not there: numpy's `rint` stands in for the quantization's round-half-even (the
  same function), numpy's float32 tanh for the GELU's, which may differ from CUDA's `tanhf` in the
  last bit (the GELU case is compared with a tolerance for that).

The reference: the CPU divides a tensor by the Python scalar q_max exactly, CUDA (which the kernel
follows, like `quant.fused_kernel.fused_fake_quant`) multiplies by its float32 reciprocal, so a
quotient that is exactly a rounding tie on the CPU may round the other way on CUDA. The script
quantizes the reference rotation's output both ways: CUDA's way must equal the kernel's bit for bit
on bfloat16 inputs; the CPU's `InputTransform` may differ only at such ties.
"""

import json
import os
import subprocess
import sys
import textwrap

import pytest

pytest.importorskip("triton")

SCRIPT = textwrap.dedent("""
    import json, sys
    import numpy as np
    import torch
    from triton.runtime import interpreter

    tl = interpreter.tl
    builder = interpreter.InterpreterBuilder
    dot, cast = builder.create_dot, builder.cast_impl

    def widened(t):
        if t.dtype.scalar == tl.bfloat16:
            return interpreter.TensorHandle((t.data.astype(np.uint32) << 16).view(np.float32), tl.float32)
        return t

    def cast_impl(self, src, dst_type):
        if src.dtype.scalar == tl.float32 and dst_type.scalar == tl.bfloat16:
            bits = src.data.astype(np.float32).view(np.uint32)
            return interpreter.TensorHandle(((bits + 0x7FFF + ((bits >> 16) & 1)) >> 16).astype(np.uint16), tl.bfloat16)
        return cast(self, src, dst_type)

    builder.create_dot = lambda self, a, b, d, *rest: dot(self, widened(a), widened(b), d, *rest)
    builder.create_fma = lambda self, x, y, z: interpreter.TensorHandle(
        (x.data.astype(np.float64) * y.data + z.data).astype(z.data.dtype), z.dtype.scalar)
    builder.cast_impl = cast_impl

    import types
    import torch.nn.functional as F
    from vlaquantbench.models.pi05.fast import gelu_quant
    from vlaquantbench.quant import fused_kernel

    def numpy_libdevice(function):
        return lambda x: tl.core.tensor(interpreter.TensorHandle(function(x.handle.data), x.handle.dtype.scalar), x.type)

    gelu_quant.libdevice = types.SimpleNamespace(tanh=numpy_libdevice(np.tanh))
    fused_kernel.libdevice = types.SimpleNamespace(rint=numpy_libdevice(np.rint))

    from vlaquantbench.quant.fused_kernel import rotated_fake_quant
    from vlaquantbench.quant.hooks import InputTransform
    from vlaquantbench.quant.transforms import BlockHadamard

    results = []
    for width, dtype, bits, producer in json.loads(sys.argv[1]):
        dtype = getattr(torch, dtype)
        generator = torch.Generator().manual_seed(width)
        # channels of very different scales, as real activations have (outliers)
        x = (torch.randn(6, width, generator=generator) * torch.rand(width, generator=generator) * 4).to(dtype)
        rotation = BlockHadamard(width)
        if producer == "gelu_tanh_mul":  # gate and up: column halves of one tensor, as the MLP has them
            gate_up = torch.cat([x, x.flip(-1)], dim=-1)
            gate, up = gate_up[:, :width], gate_up[:, width:]
            kernel = gelu_quant.gelu_rotated_fake_quant(gate, up, rotation, bits)
            x = F.gelu(gate, approximate="tanh") * up
        else:
            kernel = rotated_fake_quant(x, rotation, bits)
        rotated = rotation(x).float()
        q_max = 2 ** (bits - 1) - 1
        reciprocal = float(np.float32(1) / np.float32(q_max))
        scale = rotated.abs().amax(-1, keepdim=True).clamp_min(1e-8)
        cuda_way = (torch.clamp(torch.round(rotated / (scale * reciprocal)), -q_max - 1, q_max)
                    * (scale * reciprocal)).to(dtype)
        reference = InputTransform(rotation=rotation, act_bits=bits)(x)
        quotient = rotated / (scale / q_max)
        at_tie = (quotient - quotient.floor() - 0.5).abs() < 1e-5
        differs = kernel != reference
        results.append({
            "width": width, "block": rotation.block, "dtype": str(dtype),
            "equal_cuda_way": (kernel == cuda_way).float().mean().item(),
            "equal_reference": 1 - differs.float().mean().item(),
            "differs_off_tie": int((differs & ~at_tie).sum()),
            "max_diff_over_absmax": ((kernel.float() - reference.float()).abs() / scale).max().item(),
        })
    print(json.dumps(results))
""")


def run_kernel(cases: list) -> list[dict]:
    env = {**os.environ, "TRITON_INTERPRET": "1"}
    done = subprocess.run([sys.executable, "-c", SCRIPT, json.dumps(cases)], env=env, capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_rotated_fake_quant_equals_the_reference_transform_on_bf16_rows():
    # widths the e2e scope rotates, and the kernel's cases: 1152 (9 blocks of 128, SigLIP), 4304
    # (269 blocks of 16, SigLIP's fc2 input), 2048 (one block, 16 x 128: Gemma), 1024 (8 x 128, the
    # tile padded to 16 rows: expert), 16384 (128 x 128: Gemma down_proj), 768 (3 blocks of 2 x 128:
    # the block-diagonal outer factor)
    cases = [[1152, "bfloat16", 4, None], [4304, "bfloat16", 4, None], [2048, "bfloat16", 4, None],
             [1024, "bfloat16", 4, None], [16384, "bfloat16", 4, None], [768, "bfloat16", 8, None]]
    results = run_kernel(cases)
    for result in results:
        assert result["equal_cuda_way"] == 1.0, result
        assert result["differs_off_tie"] == 0, result
        assert result["equal_reference"] > 0.99, result


def test_rotated_fake_quant_matches_the_reference_to_float32_rounding_on_float32_rows():
    # float32 rows: the rotation's float32 sums differ from the reference's in order, so a value
    # (and a row's scale) may differ in its last bits; no value moves by a grid step
    results = run_kernel([[1152, "float32", 4, None], [4096, "float32", 4, None]])
    for result in results:
        assert result["max_diff_over_absmax"] < 1e-6, result


def test_gelu_rotated_fake_quant_equals_the_reference_transform_of_the_gelu_product():
    # pi0.5's down_proj inputs (Gemma 16,384, expert 4,096): gelu(gate) * up, rotated and quantized
    # in one kernel; tanh is numpy's here (see the module docstring), so a value whose GELU rounds
    # differently may differ
    results = run_kernel([[16384, "bfloat16", 4, "gelu_tanh_mul"], [4096, "bfloat16", 4, "gelu_tanh_mul"]])
    for result in results:
        assert result["equal_cuda_way"] > 0.999, result


@pytest.mark.parametrize("kernel,width,dtype", [("rotated", 16384, "bf16"), ("rotated", 1152, "fp32"),
                                                ("rotated", 4304, "fp32"), ("gelu_rotated", 4304, "fp32"),
                                                ("gelu_rotated", 4096, "bf16")])
def test_rotation_kernels_compile_for_hopper(kernel, width, dtype):
    """No GPU here, but Triton's own compiler runs: the kernels compile to PTX for an H100/H200
    (sm_90) with the launch `rotation_tile` chooses; bf16 rows multiply on the tensor cores (mma),
    float32 rows too (in three bf16 parts) but for blocks of at most 32 (SigLIP fc2's 16), which
    take fused multiply-adds; the quantization keeps round-half-even (`cvt.rni`)."""
    import triton
    from triton.backends.compiler import GPUTarget
    from triton.compiler import ASTSource

    from vlaquantbench.models.pi05.fast import gelu_quant
    from vlaquantbench.quant import fused_kernel
    from vlaquantbench.quant.transforms import BlockHadamard

    launch = fused_kernel.rotation_tile(width, BlockHadamard(width))
    warps = launch.pop("num_warps")
    constexprs = {name: value for name, value in launch.items() if name.isupper()}
    scalars = {"n_cols": "i32", "n_tile_rows": "i32", "q_max": "fp32", "inv_q_max": "fp32", "scale_floor": "fp32",
               "inner_ptr": "*fp32", "outer_ptr": "*fp32"}
    if kernel == "rotated":
        fn, pointers = fused_kernel._rotated_fake_quant, ("x_ptr", "y_ptr")
    else:
        fn, pointers = gelu_quant._gelu_rotated_fake_quant, ("gate_ptr", "up_ptr", "out_ptr")
        scalars |= {"gate_row_stride": "i64", "up_row_stride": "i64", "k_beta": "fp32", "k_kappa": "fp32"}
        constexprs["HAS_UP"] = True
    signature = {name: f"*{dtype}" for name in pointers} | scalars | {name: "constexpr" for name in constexprs}
    compiled = triton.compile(ASTSource(fn=fn, signature=signature, constexprs=constexprs),
                              target=GPUTarget("cuda", 90, 32), options={"num_warps": warps})
    ptx = compiled.asm["ptx"]
    assert ".target sm_90" in ptx and "cvt.rni.f32.f32" in ptx
    tensor_cores = "mma.sync" in ptx or "wgmma" in ptx
    assert tensor_cores == (dtype == "bf16" or launch["OUTER"] > 1 or launch["INNER"] > 32)
    assert "fma.rn.f32" in ptx
