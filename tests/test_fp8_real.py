"""Real FP8 kernels in the captured pi0.5 sampler (issue 33): what runs on the CPU. The input cast a
producing op computes, the FP8 weight format against the fake-quantized FP8E4M3 grid, linear groups
of packed FP8 layers (one merged weight, no second copy; the cast computed once per input), and the
refusal of a real-FP8 cell on a device without row-wise `torch._scaled_mm`. The products themselves
run on CUDA only (`benchmarks/gpu_fp8_real.py` checks them against float64 on an H200)."""

import pytest
import torch
from test_pi05_probe import CAPTURED
from torch import nn

from vlaquantbench.cells import cell_config
from vlaquantbench.errors import UserError
from vlaquantbench.models.pi05.fast import static_sampling
from vlaquantbench.models.pi05.fast.linear_groups import LinearGroup
from vlaquantbench.quant.float_grid import E4M3, fake_quant_fp8
from vlaquantbench.quant.grid import CastRows, PerTokenCast, fake_quant_activation, fma_quotient
from vlaquantbench.quant.hooks import CountingHook
from vlaquantbench.quant.input_transform import InputTransform
from vlaquantbench.quant.kernels.fp8 import Fp8DynamicLinear
from vlaquantbench.quant.kernels.packed import FP8, quantize_per_token
from vlaquantbench.runner.cell import CellRun


def _rows(seed: int, dtype=torch.float32) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    # rows of very different magnitudes, one of zeros (the scale floor), one outlier column
    x = torch.randn(6, 5, 96, generator=g) * torch.logspace(-3, 3, 5)[:, None]
    x[0, 1] = 0.0
    x[2, 3, 7] = 1e4
    return x.to(dtype)


@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
def test_a_per_token_fp8_cast_dequantizes_to_the_fake_quantized_fp8_grid(dtype):
    x = _rows(0, dtype)
    rows = PerTokenCast(FP8)(x)
    assert isinstance(rows, CastRows) and rows.shape == x.shape
    assert rows.values.dtype == FP8 and rows.scales.dtype == torch.float32 and rows.scales.shape == (6, 5, 1)
    # straightforward reference: one scale per token, max|x| / 448, values cast to e4m3
    amax = x.float().abs().amax(dim=-1, keepdim=True)
    assert torch.equal(rows.scales, amax.clamp_min(1e-8) / 448.0)
    assert torch.equal(rows.values.float(), (x.float() / rows.scales).to(FP8).float())
    # what FP8E4M3 fake quantization computes, value for value
    assert torch.equal(rows.values.float() * rows.scales, fake_quant_fp8(x.float(), E4M3, per_row=True))
    # the compiled form's quotient (one division per row) and the eager kernel's path give the same cast
    assert torch.equal(PerTokenCast(FP8)(x, fma_quotient).values.view(torch.uint8), rows.values.view(torch.uint8))
    values, scales = quantize_per_token(x.reshape(-1, 96), FP8)
    assert torch.equal(values.view(torch.uint8), rows.values.reshape(-1, 96).view(torch.uint8))


def test_a_per_token_int8_cast_dequantizes_to_the_fake_quantized_int8_grid():
    x = _rows(1)
    rows = PerTokenCast(torch.int8)(x)
    assert rows.values.dtype == torch.int8 and rows.values.abs().max() <= 127
    assert torch.equal(rows.values.float() * rows.scales, fake_quant_activation(x, 8))


def test_fp8_weights_are_stored_in_one_byte_on_the_fake_quantized_grid():
    torch.manual_seed(0)
    linear = nn.Linear(96, 40).to(torch.bfloat16)
    layer = Fp8DynamicLinear(linear)
    assert layer.weight_fp8.dtype == FP8 and layer.weight_fp8.element_size() == 1
    assert layer.weight_scale.shape == (1, 40) and layer.weight_scale.dtype == torch.float32
    assert layer.weight_fp8.untyped_storage().nbytes() == 40 * 96  # a quarter of float32, half of bf16
    # per output channel, the same values as the FP8E4M3 preset's fake-quantized weights
    dequantized = layer.weight_fp8.float() * layer.weight_scale.t()
    assert torch.equal(dequantized, fake_quant_fp8(linear.weight.float(), E4M3, per_row=True))
    # lerobot's eager Gemma stack reads q_proj.weight.dtype: shape and dtype, with no data behind them
    assert layer.weight.device.type == "meta" and layer.weight.dtype == torch.bfloat16 and layer.weight.shape == (40, 96)
    assert layer.input_cast == PerTokenCast(FP8)
    assert Fp8DynamicLinear(linear, tensorwise=True).input_cast is None  # computes its own scale


def test_the_header_records_the_packed_weight_memory():
    """int8 W8A8 (SmoothQuant's layers without smoothing) runs on the CPU; the record is the same code for fp8."""
    from vlaquantbench.quant.kernels.int8 import Int8DynamicLinear
    from vlaquantbench.quant.kernels.packed import replace_all
    from vlaquantbench.quant.scope import Selection

    torch.manual_seed(0)
    model = nn.Sequential(nn.Linear(64, 32).to(torch.bfloat16), nn.Linear(32, 16, bias=False).to(torch.bfloat16))
    selection = Selection({"llm": {"0": model[0], "1": model[1]}})
    result = replace_all(model, selection, lambda n, m: Int8DynamicLinear(m), "int8 W8A8")
    released = 2 * (64 * 32 + 32 + 32 * 16)
    packed = (64 * 32 + 32 * 16) + 4 * (32 + 16) + 2 * 32  # int8 weights, float32 scales, the bf16 bias
    assert result.details["weight_memory"] == {"layers": 2, "released_bytes": released, "packed_bytes": packed,
                                               "ratio": packed / released}
    assert result.details["kernels"] == {Int8DynamicLinear.CPU_KERNEL: 2}  # on the CPU: torch._int_mm, not Triton
    assert "torch._int_mm" in Int8DynamicLinear.CPU_KERNEL


def _fp8_layers(sizes, hooks=True):
    torch.manual_seed(0)
    layers = [Fp8DynamicLinear(nn.Linear(64, n).to(torch.bfloat16)) for n in sizes]
    return layers, [CountingHook(layer, InputTransform()) for layer in layers] if hooks else []


def test_a_group_of_fp8_layers_is_one_merged_weight_and_its_producer_casts_once():
    layers, hooks = _fp8_layers([48, 16, 16])
    originals = [layer.weight_fp8.clone() for layer in layers]
    group = LinearGroup(layers)
    assert group.fused and group.input_quantization == PerTokenCast(FP8)
    merged = group.merged
    assert merged.weight_fp8.shape == (80, 64) and merged.weight_scale.shape == (1, 80) and merged.bias.shape == (80,)
    # the members now view the merged weight: one copy in memory, the same values
    storages = {layer.weight_fp8.untyped_storage().data_ptr() for layer in layers}
    assert storages == {merged.weight_fp8.untyped_storage().data_ptr()}
    assert all(torch.equal(a.view(torch.uint8), b.weight_fp8.view(torch.uint8)) for a, b in zip(originals, layers))
    x, weight = torch.randn(2, 7, 64).to(torch.bfloat16), torch.randn(64)
    hidden, rows = group.input_from(static_sampling.add_rms_norm, (x, x, weight, 1e-6))
    assert isinstance(rows, CastRows) and rows.shape == (2, 7, 64)
    expected = PerTokenCast(FP8)(static_sampling.rms_norm(x + x, weight, 1e-6))
    assert torch.equal(rows.values.view(torch.uint8), expected.values.view(torch.uint8))
    assert torch.equal(rows.scales, expected.scales) and torch.equal(hidden, x + x)
    assert [hook.calls for hook in hooks] == [1, 1, 1]  # each member's quantizer counted its run


def test_fp8_layers_without_a_plain_counting_hook_run_as_modules():
    layers, _ = _fp8_layers([16, 16], hooks=False)
    assert not LinearGroup(layers).fused  # nothing would count their runs
    layers, hooks = _fp8_layers([16, 16])
    hooks[1].transform = InputTransform(act_bits=8)  # a layer that also fake-quantizes its input
    assert not LinearGroup(layers).fused
    tensorwise = [Fp8DynamicLinear(nn.Linear(64, 16), tensorwise=True) for _ in range(2)]
    for layer in tensorwise:
        CountingHook(layer, InputTransform())
    assert not LinearGroup(tensorwise).fused


def test_a_real_fp8_cell_on_the_cpu_is_refused_before_any_episode(tmp_path):
    run = CellRun(cell_config("libero/libero_spatial/pi05/fp8-W8A8-e2e", CAPTURED), tmp_path, progress=False)
    with pytest.raises(UserError, match=r"method 'fp8' runs real FP8 kernels .* compute capability 8.9 .* is on cpu"):
        run.prepare()
    assert not any(tmp_path.iterdir())
