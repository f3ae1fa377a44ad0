"""Real INT8 (W8A8) and INT4 (W4A16) kernels in the captured pi0.5 sampler (issue 33), on the CPU,
where `torch._int_mm` and tinygemm's CPU form run: int8 layers group like FP8 ones (one merged
int8 weight, the input cast to int8 rows by its producer), their products equal the definition,
int4 layers pack inputs of any size, and the captured sampler's actions on the quantized demo
pi0.5 match lerobot's eager `sample_actions` on the same quantized model."""

import pytest
import torch
from test_pi05_fast import REL_TOL, _inputs, _rel
from torch import nn

from vlaquantbench.cells import cell_config
from vlaquantbench.errors import UserError
from vlaquantbench.models import get_model_spec
from vlaquantbench.models.pi05.fast import CapturedSampler, static_sampling
from vlaquantbench.models.pi05.fast.linear_groups import LinearGroup
from vlaquantbench.quant import QuantConfig, quantize_
from vlaquantbench.quant.grid import CastRows, PerTokenCast
from vlaquantbench.quant.hooks import CountingHook
from vlaquantbench.quant.input_transform import InputTransform
from vlaquantbench.quant.kernels.int4 import Int4WeightOnlyLinear
from vlaquantbench.quant.kernels.int8 import Int8DynamicLinear, dequantize_int32
from test_fp8_real import CAPTURED


def _int8_layers(sizes, smooth=None):
    torch.manual_seed(0)
    layers = [Int8DynamicLinear(nn.Linear(64, n).to(torch.bfloat16), smooth) for n in sizes]
    return layers, [CountingHook(layer, InputTransform()) for layer in layers]


def test_a_group_of_int8_layers_is_one_merged_int8_weight_cast_by_its_producer():
    layers, hooks = _int8_layers([48, 16, 16])
    originals = [layer.weight_int8.clone() for layer in layers]
    group = LinearGroup(layers)
    assert group.fused and group.input_quantization == PerTokenCast(torch.int8)
    merged = group.merged
    assert merged.weight_int8.shape == (80, 64) and merged.weight_scale.shape == (1, 80) and merged.smooth is None
    assert {layer.weight_int8.untyped_storage().data_ptr() for layer in layers} == {merged.weight_int8.untyped_storage().data_ptr()}
    assert all(torch.equal(a, b.weight_int8) for a, b in zip(originals, layers))
    x, weight = torch.randn(2, 7, 64).to(torch.bfloat16), torch.randn(64)
    hidden, rows = group.input_from(static_sampling.add_rms_norm, (x, x, weight, 1e-6))
    normed = static_sampling.rms_norm(x + x, weight, 1e-6)
    expected = PerTokenCast(torch.int8)(normed)
    assert isinstance(rows, CastRows) and rows.values.dtype == torch.int8
    assert torch.equal(rows.values, expected.values) and torch.equal(rows.scales, expected.scales)
    # the merged product equals the members run as modules (each quantizing the norm's output itself)
    with torch.no_grad():
        modules = [layer(normed) for layer in layers]
        assert all(torch.equal(a, b) for a, b in zip(group(rows), modules))
    assert [hook.calls for hook in hooks] == [2, 2, 2]  # the producer's run, then each module's own


def test_int8_products_are_the_exact_integer_sums_rescaled_once():
    layers, _ = _int8_layers([24])
    layer = layers[0]
    rows = PerTokenCast(torch.int8)(torch.randn(5, 64))  # 5 rows: padded to the kernel's 32 and cut back
    with torch.no_grad():
        out = layer.forward_cast(rows)
    exact = rows.values.double() @ layer.weight_int8.double().t()  # integers: exact in float64
    expected = ((exact.float() * rows.scales) * layer.weight_scale).to(torch.bfloat16) + layer.bias
    assert out.dtype == torch.bfloat16 and torch.equal(out, expected)
    acc = torch.tensor([[3, -7]], dtype=torch.int32)
    assert torch.equal(dequantize_int32(acc, torch.tensor([[0.5]]), torch.tensor([[2.0, 0.25]]), torch.float32),
                       torch.tensor([[3.0, -0.875]]))


def test_smoothed_int8_layers_quantize_their_own_input():
    layers, _ = _int8_layers([16, 16], smooth=torch.rand(64) + 0.5)
    assert layers[0].input_cast is None and not LinearGroup(layers).fused


@pytest.mark.parametrize("in_features", [256, 200, 32])
def test_int4_layers_pack_any_input_size_and_compute_their_dequantized_weights(in_features):
    torch.manual_seed(0)
    linear = nn.Linear(in_features, 48).to(torch.bfloat16)
    layer = Int4WeightOnlyLinear(linear, group_size=128)
    assert layer.padded_in % 128 == 0 and layer.padded_in >= in_features
    # the definition: asymmetric 4-bit groups of 128 along the zero-padded input
    w = nn.functional.pad(linear.weight.float(), (0, layer.padded_in - in_features)).reshape(48, -1, 128)
    low, high = w.amin(-1, keepdim=True), w.amax(-1, keepdim=True)
    scale = (high - low) / 15
    dequantized = (torch.round((w - low) / scale).clamp(0, 15) * scale + low).reshape(48, -1)[:, :in_features]
    x = torch.randn(3, 9, in_features).to(torch.bfloat16)
    with torch.no_grad():
        out = layer(x)
    expected = x.float() @ dequantized.t() + linear.bias.float()
    assert out.shape == (3, 9, 48) and out.dtype == torch.bfloat16
    assert _rel(out.float(), expected) < 1e-2  # bf16 scales and output
    assert _rel(out.float(), x.float() @ linear.weight.float().t() + linear.bias.float()) > 1e-2  # 4 bits, not 16
    # weights in half a byte: a quarter of bf16 (plus a scale and zero per group)
    assert layer.weight_int4.untyped_storage().nbytes() == 48 * layer.padded_in // 2


def test_the_int_cells_parse_and_refuse_other_presets():
    assert cell_config("libero/libero_spatial/pi05/int8_dynamic-W8A8-e2e", CAPTURED)["method"] == "int8_dynamic"
    assert cell_config("libero/libero_spatial/pi05/int4wo-W4-e2e", CAPTURED)["method"] == "int4wo"
    with pytest.raises(UserError, match="method 'int8_dynamic' implements W8A8"):
        cell_config("libero/libero_spatial/pi05/int8_dynamic-W4A8-e2e", CAPTURED)


@pytest.fixture(scope="module")
def unquantized_actions():
    model = get_model_spec("pi05").build(variant="demo", device="cpu", seed=0)
    images, img_masks, tokens, masks, noise = _inputs(batch=2, seed=1)
    with torch.no_grad():
        return model.sample_actions(images, img_masks, tokens, masks, noise=noise.clone(), num_steps=2)


# Measured: the captured sampler's actions equal lerobot's on the quantized demo model (relative L2
# 0.0 for both); against the unquantized model 1.6e-2 (int8) and 0.15 (int4).
@pytest.mark.parametrize("preset, method", [("W8A8", "int8_dynamic"), ("W4", "int4wo")])
def test_captured_sampler_with_real_int_kernels_matches_lerobot_on_the_quantized_model(preset, method,
                                                                                     unquantized_actions):
    spec = get_model_spec("pi05")
    model = spec.build(variant="demo", device="cpu", seed=0)
    config = QuantConfig.from_preset(preset, scope="e2e", method=method)
    report = quantize_(model, config, config.select(model, spec.components))
    packed = Int8DynamicLinear if method == "int8_dynamic" else Int4WeightOnlyLinear
    assert len(report.result.hooks) > 100
    assert all(isinstance(model.get_submodule(name), packed) for name in report.result.hooks)
    images, img_masks, tokens, masks, noise = _inputs(batch=2, seed=1)
    with torch.no_grad():
        expected = model.sample_actions(images, img_masks, tokens, masks, noise=noise.clone(), num_steps=2)
        sampler = CapturedSampler(model, num_steps=2)
        actual = sampler(images, img_masks, tokens, masks, noise)
    groups = sampler._model_groups()
    every = [g for layer in groups.vision + groups.prefix + groups.expert for g in (layer.qkv, layer.out, layer.mlp_in, layer.mlp_out)]
    assert all((g.cast is not None) == (method == "int8_dynamic") for g in every)
    assert report.unfired() == []
    assert torch.isfinite(actual).all() and _rel(actual, expected) < REL_TOL
    assert _rel(expected, unquantized_actions) > 5e-3  # the kernels quantize


def test_a_header_whose_weight_memory_or_kernels_are_malformed_is_refused_naming_the_field():
    from vlaquantbench.records.schema import EpisodeCheck

    header = {"model": "pi05", "benchmark": "libero", "suite": "libero_spatial", "seed": 0, "episodes_per_task": 1,
              "max_steps": 10, "quant_report": {"weight_memory": {"layers": 2, "released_bytes": 100, "packed_bytes": 52,
                                                                  "ratio": 0.52},
                                                "kernels": {Int8DynamicLinear.KERNEL: 2}}}
    EpisodeCheck(header, "h.json")
    with pytest.raises(UserError, match=r"h.json: run header: quant_report.weight_memory.packed_bytes"):
        EpisodeCheck({**header, "quant_report": {"weight_memory": {"layers": 2, "released_bytes": 1, "packed_bytes": "52"}}},
                     "h.json")
    with pytest.raises(UserError, match=r"quant_report.kernels"):
        EpisodeCheck({**header, "quant_report": {"kernels": {"x": 0}}}, "h.json")
