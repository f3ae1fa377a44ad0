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
    from vlaquantbench.models.pi05.fast import gelu_quant, rotated_norms, static_sampling
    from vlaquantbench.quant import fused_kernel

    def numpy_libdevice(function):
        return lambda x: tl.core.tensor(interpreter.TensorHandle(function(x.handle.data), x.handle.dtype.scalar), x.type)

    gelu_quant.libdevice = types.SimpleNamespace(tanh=numpy_libdevice(np.tanh))
    fused_kernel.libdevice = types.SimpleNamespace(rint=numpy_libdevice(np.rint))
    rotated_norms.libdevice = types.SimpleNamespace(
        rsqrt=numpy_libdevice(lambda a: (np.float32(1) / np.sqrt(a)).astype(np.float32)))

    from vlaquantbench.quant.fused_kernel import rotated_fake_quant
    from vlaquantbench.quant.hadamard import BlockHadamard
    from vlaquantbench.quant.input_transform import InputTransform

    results = []
    for width, dtype, bits, producer, *tokens in json.loads(sys.argv[1]):
        shared = {"tokens_per_program": tokens[0]} if tokens else {}  # tokens sharing a kernel program
        dtype = getattr(torch, dtype)
        generator = torch.Generator().manual_seed(width)
        # channels of very different scales, as real activations have (outliers)
        x = (torch.randn(6, width, generator=generator) * torch.rand(width, generator=generator) * 4).to(dtype)
        rotation = BlockHadamard(width)
        hidden_equal = None
        if producer in ("ada_rms_norm", "gated_add_ada_rms_norm"):  # the action expert's norms, 2 samples x 3 tokens
            modulation = (torch.randn(2, 1, 3 * width, generator=generator) * 0.5).chunk(3, dim=-1)
            scale, shift, gate = modulation[0], modulation[1], modulation[2].to(dtype)
            hidden = x.view(2, 3, width)
            if producer == "ada_rms_norm":
                kernel = rotated_norms.ada_rms_norm_rotated_fake_quant(hidden, scale, shift, 1e-6, rotation=rotation,
                                                                       bits=bits, **shared)
                x = static_sampling.ada_rms_norm(hidden, scale, shift, 1e-6)
            else:
                update = x.flip(-1).view(2, 3, width) * 3
                new_hidden, kernel = rotated_norms.gated_add_ada_rms_norm_rotated_fake_quant(
                    hidden, update, gate, scale, shift, 1e-6, rotation=rotation, bits=bits, **shared)
                reference_hidden, x = static_sampling.gated_add_ada_rms_norm(hidden, update, gate, scale, shift, 1e-6)
                hidden_equal = bool(torch.equal(new_hidden, reference_hidden))
            kernel, x = kernel.reshape(6, width), x.reshape(6, width)
        elif producer == "merge_heads":  # 2 samples x 3 tokens, heads read from B x H x L x D
            heads = x.view(2, 3, width // 256, 256).transpose(1, 2)
            kernel = rotated_norms.merge_heads_rotated_fake_quant(heads, rotation=rotation, bits=bits, **shared)
            kernel = kernel.reshape(6, width)
            x = static_sampling.merge_heads(heads).reshape(6, width)
        elif producer == "gelu_tanh_mul":  # gate and up: column halves of one tensor, as the MLP has them
            gate_up = torch.cat([x, x.flip(-1)], dim=-1)
            gate, up = gate_up[:, :width], gate_up[:, width:]
            kernel = gelu_quant.gelu_rotated_fake_quant(gate, up, rotation, bits, **shared)
            x = F.gelu(gate, approximate="tanh") * up
        else:
            kernel = rotated_fake_quant(x, rotation, bits, **shared)
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
            "width": width, "block": rotation.block, "dtype": str(dtype), "hidden_equal": hidden_equal,
            "equal_cuda_way": (kernel == cuda_way).float().mean().item(),
            "equal_reference": 1 - differs.float().mean().item(),
            "differs_off_tie": int((differs & ~at_tie).sum()),
            "max_diff_over_absmax": ((kernel.float() - reference.float()).abs() / scale).max().item(),
        })
    print(json.dumps(results))
""")


def run_kernel(cases: list) -> list[dict]:
    """Each case (width, dtype, bits, producer[, tokens per program]): its kernel on 6 tokens."""
    env = {**os.environ, "TRITON_INTERPRET": "1"}
    done = subprocess.run([sys.executable, "-c", SCRIPT, json.dumps(cases)], env=env, capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


# The cases of the tests below: widths the e2e scope rotates, and the kernel's cases: 1152 (9 blocks of 128,
# SigLIP), 4304 (269 blocks of 16, SigLIP's fc2 input), 2048 (one block, 16 x 128: Gemma), 1024 (8 x 128, the tile
# padded to 16 rows: expert), 16384 (128 x 128: Gemma down_proj), 768 (3 blocks of 2 x 128: the block-diagonal
# outer factor).
BF16_ROWS = [[1152, "bfloat16", 4, None], [4304, "bfloat16", 4, None], [2048, "bfloat16", 4, None],
             [1024, "bfloat16", 4, None], [16384, "bfloat16", 4, None], [768, "bfloat16", 8, None]]
FLOAT32_ROWS = [[1152, "float32", 4, None], [4096, "float32", 4, None]]
GELU = [[16384, "bfloat16", 4, "gelu_tanh_mul"], [4096, "bfloat16", 4, "gelu_tanh_mul"]]
NORMS_AND_HEADS = [[1024, "bfloat16", 4, "ada_rms_norm"], [1024, "bfloat16", 4, "gated_add_ada_rms_norm"],
                   [2048, "bfloat16", 8, "gated_add_ada_rms_norm"], [2048, "bfloat16", 4, "merge_heads"]]
# `tokens_per_program`: 8 tokens of 1,024, 2,048 or 1,152 in one program (the 6 here fill part of it, the rest
# masked), 4 of 4,096 (two programs), each beside the same case at one token per program.
ALONE = [[1024, "bfloat16", 4, None], [1152, "float32", 4, None], [4096, "bfloat16", 4, "gelu_tanh_mul"],
         [1024, "bfloat16", 4, "gated_add_ada_rms_norm"], [2048, "bfloat16", 4, "merge_heads"]]
SHARED = [[*case, n] for case, n in zip(ALONE, [8, 8, 4, 8, 8], strict=True)]


@pytest.fixture(scope="module")
def kernel():
    """Every case above run once, in one interpreter (its start, Triton's interpreter and the patches above, is
    most of a case's time; each case seeds its own input): a function from a test's cases to their results."""
    cases = [case for group in (BF16_ROWS, FLOAT32_ROWS, GELU, NORMS_AND_HEADS, ALONE, SHARED) for case in group]
    distinct = list(dict.fromkeys(json.dumps(case) for case in cases))
    results = dict(zip(distinct, run_kernel([json.loads(case) for case in distinct]), strict=True))
    return lambda group: [results[json.dumps(case)] for case in group]


def test_rotated_fake_quant_equals_the_reference_transform_on_bf16_rows(kernel):
    for result in kernel(BF16_ROWS):
        assert result["equal_cuda_way"] == 1.0, result
        assert result["differs_off_tie"] == 0, result
        assert result["equal_reference"] > 0.99, result


def test_rotated_fake_quant_matches_the_reference_to_float32_rounding_on_float32_rows(kernel):
    # float32 rows: the rotation's float32 sums differ from the reference's in order, so a value
    # (and a row's scale) may differ in its last bits; no value moves by a grid step
    for result in kernel(FLOAT32_ROWS):
        assert result["max_diff_over_absmax"] < 1e-6, result


def test_gelu_rotated_fake_quant_equals_the_reference_transform_of_the_gelu_product(kernel):
    # pi0.5's down_proj inputs (Gemma 16,384, expert 4,096): gelu(gate) * up, rotated and quantized
    # in one kernel; tanh is numpy's here (see the module docstring), so a value whose GELU rounds
    # differently may differ
    for result in kernel(GELU):
        assert result["equal_cuda_way"] > 0.999, result


def test_norm_and_head_merge_rotated_kernels_equal_the_ops_then_the_reference_transform(kernel):
    # pi0.5's expert (1,024 wide: q/k/v and gate/up read its AdaRMS norms) and its attention output
    # (2,048: 8 heads of 256); the norm's mean square sums in another order than torch's and rsqrt
    # is numpy's here, so a normalized value may round differently before it is rotated
    results = kernel(NORMS_AND_HEADS)
    for result in results:
        assert result["equal_cuda_way"] > 0.999, result
        assert result["max_diff_over_absmax"] < 0.15, result  # at most a step of the 4-bit grid
    assert results[1]["hidden_equal"] and results[2]["hidden_equal"]  # the residual add, bit for bit
    assert results[3]["equal_cuda_way"] == 1.0 and results[3]["differs_off_tie"] == 0  # a gather, then the kernel


def test_tokens_sharing_a_program_give_what_a_program_each_gives(kernel):
    # every token still rotated and quantized alone
    for one, several in zip(kernel(ALONE), kernel(SHARED), strict=True):
        assert several == one


def test_tokens_per_program_past_the_tile_limit_is_refused_naming_it():
    from vlaquantbench.quant import fused_kernel
    from vlaquantbench.quant.hadamard import BlockHadamard

    with pytest.raises(ValueError, match="tokens_per_program"):
        fused_kernel.rotation_tile(4096, BlockHadamard(4096), 50, tokens_per_program=8)  # 8 x 32 tile rows
    with pytest.raises(ValueError, match="tokens_per_program"):
        fused_kernel.rotation_tile(1024, BlockHadamard(1024), 50, tokens_per_program=3)


@pytest.mark.parametrize("kernel,width,dtype,tokens", [
    ("rotated", 16384, "bf16", 1), ("rotated", 1152, "fp32", 1), ("rotated", 4304, "fp32", 1),
    ("gelu_rotated", 4304, "fp32", 1), ("gelu_rotated", 4096, "bf16", 1), ("ada_rms_norm", 1024, "bf16", 1),
    ("merge_heads", 2048, "bf16", 1), ("rotated", 1024, "bf16", 8), ("rotated", 1152, "fp32", 8),
    ("gelu_rotated", 4096, "bf16", 4), ("ada_rms_norm", 1024, "bf16", 8)])
def test_rotation_kernels_compile_for_hopper(kernel, width, dtype, tokens):
    """No GPU here, but Triton's own compiler runs: the kernels compile to PTX for an H100/H200
    (sm_90) with the launch `rotation_tile` chooses (one token per program, and several); bf16 rows
    multiply on the tensor cores (mma), float32 rows too (in three bf16 parts) but for blocks of at
    most 32 (SigLIP fc2's 16), which take fused multiply-adds; the quantization keeps
    round-half-even (`cvt.rni`)."""
    import triton
    from triton.backends.compiler import GPUTarget
    from triton.compiler import ASTSource

    from vlaquantbench.models.pi05.fast import gelu_quant, rotated_norms
    from vlaquantbench.quant import fused_kernel
    from vlaquantbench.quant.hadamard import BlockHadamard

    launch = fused_kernel.rotation_tile(width, BlockHadamard(width), tokens_per_program=tokens)
    warps = launch.pop("num_warps")
    launch.pop("grid")
    constexprs = {name: value for name, value in launch.items() if name.isupper()}
    scalars = {"n_tokens": "i32", "n_cols": "i32", "n_tile_rows": "i32", "q_max": "fp32", "inv_q_max": "fp32",
               "scale_floor": "fp32", "inner_ptr": "*fp32", "outer_ptr": "*fp32", "inner_signs_ptr": "*bf16",
               "outer_signs_ptr": "*bf16"}
    if kernel == "rotated":
        fn, pointers = fused_kernel._rotated_fake_quant, ("x_ptr", "y_ptr")
    elif kernel == "gelu_rotated":
        fn, pointers = gelu_quant._gelu_rotated_fake_quant, ("gate_ptr", "up_ptr", "out_ptr")
        scalars |= {"gate_row_stride": "i64", "up_row_stride": "i64", "k_beta": "fp32", "k_kappa": "fp32"}
        constexprs["HAS_UP"] = True
    elif kernel == "ada_rms_norm":
        fn = rotated_norms._ada_rms_norm_rotated_fake_quant
        pointers = ("hidden_ptr", "update_ptr", "gate_ptr", "hidden_out_ptr", "out_ptr")
        scalars |= {"scale_ptr": "*fp32", "shift_ptr": "*fp32", "tokens": "i32", "gate_batch_stride": "i32",
                    "scale_batch_stride": "i32", "shift_batch_stride": "i32", "inv_n_cols": "fp32", "eps": "fp32"}
        constexprs["HAS_RESIDUAL"] = True
    else:
        fn, pointers = rotated_norms._merge_heads_rotated_fake_quant, ("src_ptr", "out_ptr")
        scalars |= {name: "i32" for name in ("tokens", "head_dim", "batch_stride", "head_stride", "token_stride")}
    signature = {name: f"*{dtype}" for name in pointers} | scalars | {name: "constexpr" for name in constexprs}
    compiled = triton.compile(ASTSource(fn=fn, signature=signature, constexprs=constexprs),
                              target=GPUTarget("cuda", 90, 32), options={"num_warps": warps})
    ptx = compiled.asm["ptx"]
    assert ".target sm_90" in ptx and "cvt.rni.f32.f32" in ptx
    tensor_cores = "mma.sync" in ptx or "wgmma" in ptx
    assert tensor_cores == (dtype == "bf16" or launch["OUTER"] > 1 or launch["INNER"] > 32)
    assert "fma.rn.f32" in ptx
