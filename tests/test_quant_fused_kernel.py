"""`fuse_activation_hooks` swaps the transform of quantize_'s counting hooks without changing what
they compute or count (CPU: the reference arithmetic runs; the fused kernel's bit-equality on CUDA
is checked by benchmarks/gpu_policy_inference.py, `checks.fused_equal_fraction`)."""

from fractions import Fraction

import numpy as np
import torch

from vlaquantbench.quant.fused_kernel import FusedInputTransform, fuse_activation_hooks
from vlaquantbench.models import get_model_spec
from vlaquantbench.quant import QuantConfig, quantize_


def test_fused_hooks_keep_results_and_counts():
    spec = get_model_spec("pi05")
    model = spec.build(variant="demo", device="cpu", seed=0)
    config = QuantConfig.from_preset("W4A4", scope="ah", only=["*mlp*"])
    report = quantize_(model, config, config.select(model, spec.components))
    layer = model.paligemma_with_expert.gemma_expert.model.layers[0].mlp
    x = torch.randn(2, 50, layer.gate_proj.in_features)
    with torch.no_grad():
        reference = layer(x)
        calls_before = report.hook_calls()
        assert fuse_activation_hooks(report) == len(report.result.hooks) == 56  # 54 expert MLP projections + time_mlp_in/out
        assert all(isinstance(h.transform, FusedInputTransform) for h in report.result.hooks.values())
        fused = layer(x)
    assert torch.equal(fused, reference)
    calls = report.hook_calls()
    prefix = "paligemma_with_expert.gemma_expert.model.layers.0.mlp."
    for proj in ("gate_proj", "up_proj", "down_proj"):
        assert calls[prefix + proj] == calls_before[prefix + proj] + 1
    assert fuse_activation_hooks(report) == 56  # idempotent: no double wrapping
    assert all(not isinstance(h.transform.reference, FusedInputTransform) for h in report.result.hooks.values())


def _fma32(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """float32 a * b + c with one rounding (what `tl.fma` computes): the product is exact in float64;
    the sum is rounded once to float64 and then to float32, which differs from one rounding only
    where the float64 sum lies exactly halfway between two float32 values -- resolved exactly there."""
    total = a.astype(np.float64) * b.astype(np.float64) + c.astype(np.float64)
    out = total.astype(np.float32)
    neighbour = np.where(out.astype(np.float64) < total, np.nextafter(out, np.float32(np.inf)),
                         np.nextafter(out, np.float32(-np.inf)))
    for i in np.flatnonzero((out.astype(np.float64) + neighbour.astype(np.float64)) / 2 == total):
        exact = Fraction(float(a[i])) * Fraction(float(b[i])) + Fraction(float(c[i]))
        out[i] = min((out[i], neighbour[i]), key=lambda v: (abs(Fraction(float(v)) - exact),
                                                           int(np.float32(v).view(np.uint32)) & 1))
    return out


def test_kernels_quotient_by_corrected_reciprocal_is_the_ieee_quotient():
    """The Triton quantizers (`fused_kernel.fake_quant_scaled`) divide by the row's scale without a
    division per value: q0 = x * RN(1/scale), then q = fma(fma(-q0, scale, x), RN(1/scale), q0)
    (Markstein's correction). Replayed here in float32 against `quant.grid.fake_quant_activation`
    itself -- torch's IEEE division on the CPU -- for every bf16 value up to the row's absmax and
    every bf16 absmax in a binade (powers of two scale both alike): the quantized values are equal,
    and so are the quotients away from underflow; the uncorrected product q0 alone rounds some
    values to the other level."""
    from vlaquantbench.quant.fused_kernel import fake_quant_row_args
    from vlaquantbench.quant.grid import fake_quant_activation

    bf16 = (np.arange(2 ** 16, dtype=np.uint32) << 16).view(np.float32)
    bf16 = bf16[np.isfinite(bf16)]
    for bits in (4, 8):
        q_max, _, floor = (np.float32(v) for v in fake_quant_row_args(bits))
        got, expected, uncorrected = [], [], []
        for significand in range(128):
            absmax = np.float32(1 + significand / 128)
            x = bf16[np.abs(bf16) <= absmax]
            row = np.concatenate([x, [absmax]]).astype(np.float32)  # the row's absmax is its own
            # The row's scale as torch computes it on the CPU, a division by q_max (on CUDA torch
            # multiplies by the reciprocal, as the kernels do): here the quotient by it is the question.
            scale = np.float32(max(absmax, floor)) / q_max
            inv_scale = np.float32(1) / scale
            q0 = row * inv_scale
            q = _fma32(_fma32(-q0, np.full_like(row, scale), row), np.full_like(row, inv_scale), q0)
            normal = np.abs(row / scale) >= 2.0 ** -100  # Markstein's theorem excludes underflow; those round to 0
            assert np.array_equal(q[normal], (row / scale)[normal])  # the quotient itself, as IEEE division rounds it
            got.append(np.clip(np.rint(q), -q_max - 1, q_max) * scale)
            uncorrected.append(np.clip(np.rint(q0), -q_max - 1, q_max) * scale)
            expected.append(fake_quant_activation(torch.from_numpy(row)[None], bits)[0].numpy())
        got, expected, uncorrected = (np.concatenate(v) for v in (got, expected, uncorrected))
        assert got.size > 700_000 and np.array_equal(got, expected)
        assert (uncorrected != expected).sum() > 10


def test_inductor_compiles_the_corrected_reciprocal_quotient_to_the_ieee_quotient():
    """The compiled norms and head merges quantize with `quant.grid.fma_quotient` (the quotient the
    `Inductor` compiler names): inductor under `emulate_precision_casts` makes its `addcmul`s fused
    multiply-adds (`std::fma` here on the CPU, `tl.fma` in Triton), and the quantized values equal
    IEEE division's, the hooks', for every bf16 value up to the row's absmax and every bf16 absmax
    in a binade, where the uncorrected product rounds some values to the other level. (Eager CUDA
    rounds `addcmul`'s product before adding, so the form is for compiled code only.)"""
    from vlaquantbench.models.pi05.fast import static_sampling as pi05_static
    from vlaquantbench.quant.grid import fake_quant_activation, fma_quotient
    from vlaquantbench.quant.hooks import quantizing_op

    assert pi05_static.inductor.quotient is fma_quotient
    bf16 = (np.arange(2 ** 16, dtype=np.uint32) << 16).view(np.float32)
    bf16 = np.sort(bf16[np.isfinite(bf16) & (np.abs(bf16) <= 2)])
    rows = []
    for significand in range(128):  # one row per absmax; values above it are zeroed (0 stays 0)
        absmax = np.float32(1 + significand / 128)
        rows.append(np.concatenate([np.where(np.abs(bf16) <= absmax, bf16, 0), [absmax]]))
    x = torch.from_numpy(np.stack(rows).astype(np.float32)).to(torch.bfloat16)
    for bits in (4, 8):
        compiled = quantizing_op(torch.clone, bits, pi05_static.inductor)(x)
        assert torch.equal(compiled, fake_quant_activation(x, bits))
        uncorrected = fake_quant_activation(x, bits, lambda values, scale: values * torch.div(1.0, scale))
        assert (uncorrected != compiled).sum() > 10
