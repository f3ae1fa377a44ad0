"""Real-kernel quantization methods behind `quantize_` (vlaquantbench.quant.kernels), on a small
real `transformers` LlamaModel on the CPU: int8 W8A8 through `torch._int_mm`, FP8 with tensor-wise
scales through `torch._scaled_mm` (row-wise FP8, int4 and bitsandbytes need a GPU; benchmarks/gpu_fp8_real.py
times FP8, INT8 and INT4 in pi0.5 on one), eager and compiled by inductor layer by layer."""

import importlib.util

import pytest
import torch
from torch._dynamo.utils import counters
from transformers import LlamaConfig, LlamaModel

from vlaquantbench.errors import UserError
from vlaquantbench.models.registry import Component
from vlaquantbench.quant import CalibrationSettings, QuantConfig, quantize_, registered_methods
from vlaquantbench.quant.calibration import observe, smoothing_factors
from vlaquantbench.quant.kernels.fp8 import Fp8DynamicLinear, Fp8StaticLinear
from vlaquantbench.quant.kernels.int8 import Int8DynamicLinear
from vlaquantbench.quant.kernels.packed import FP8_MAX

COMPONENTS = {"llm": Component(roots=("layers",))}


def _llama(seed=0, width=64):
    torch.manual_seed(seed)
    config = LlamaConfig(hidden_size=width, intermediate_size=2 * width, num_hidden_layers=2, num_attention_heads=4,
                         num_key_value_heads=4, vocab_size=100)
    return LlamaModel(config).eval()


def _rel(a, b):
    return ((a - b).norm() / b.norm()).item()


def _w8a8(method, model, x):
    """The W8A8 config of `method`; SmoothQuant's with its default migration from statistics on `x`."""
    if method != "smoothquant":
        return QuantConfig.from_preset("W8A8", scope="llm", method=method)
    settings = CalibrationSettings(alpha=0.85, quantile=None, components=("llm",))
    return QuantConfig.from_preset("W8A8", scope="llm", method=method, calibration=settings, stats=_observed(model, x))


def test_methods_are_registered():
    assert {"nf4", "int8", "int4wo", "smoothquant", "fp8", "fp8_tensor", "fp8_static"} <= set(registered_methods())


@pytest.mark.parametrize("method, fmt, tolerance", [("smoothquant", "int8", 0.02), ("fp8_tensor", "FP8 e4m3", 0.1)])
def test_kernel_method_replaces_layers_and_stays_close(method, fmt, tolerance):
    model = _llama()
    x = torch.randn(1, 20, 64, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        reference = model(inputs_embeds=x).last_hidden_state
        config = _w8a8(method, model, x)
        report = quantize_(model, config, config.select(model, COMPONENTS))
        out = model(inputs_embeds=x).last_hidden_state
    assert report.components == {"llm": {"layers": 14, "params": 2 * (4 * 64 * 64 + 3 * 64 * 128)}}
    assert not any(isinstance(m, torch.nn.Linear) for m in model.layers.modules())
    assert report.unfired() == []  # each packed layer's counting hook saw the forward pass
    assert fmt in report.result.format
    err = _rel(out, reference)
    assert 0 < err < tolerance  # quantized (not a no-op) yet close


def test_int8_w8a8_matches_its_definition():
    """`torch._int_mm` result equals (round(x/s_x) @ round(W/s_w)^T) * s_x * s_w computed in float."""
    linear = torch.nn.Linear(48, 40)
    x = torch.randn(3, 5, 48)
    layer = Int8DynamicLinear(linear)
    s_w = linear.weight.abs().amax(dim=1, keepdim=True) / 127
    w_q = torch.round(linear.weight / s_w).clamp(-128, 127)
    s_x = x.reshape(-1, 48).abs().amax(dim=-1, keepdim=True) / 127
    x_q = torch.round(x.reshape(-1, 48) / s_x).clamp(-128, 127)
    expected = (x_q @ w_q.t()) * s_x * s_w.t() + linear.bias
    with torch.no_grad():
        assert torch.allclose(layer(x).reshape(-1, 40), expected, rtol=1e-5, atol=1e-5)


def test_smoothquant_smooths_by_default_and_refuses_to_run_without_statistics():
    model = _llama()
    x = torch.randn(1, 20, 64, generator=torch.Generator().manual_seed(1)) * torch.logspace(-1, 1, 64)  # outlier channels
    config = _w8a8("smoothquant", model, x)
    q_proj = model.layers[0].self_attn.q_proj
    stats = config.stats.layers["layers.0.self_attn.q_proj"]
    expected = smoothing_factors(stats.absmax, q_proj.weight, 0.85)
    report = quantize_(model, config, config.select(model, COMPONENTS))
    packed = model.layers[0].self_attn.q_proj
    assert torch.equal(packed.smooth, expected.float()) and report.result.calibrated == set(report.selected)
    assert "SmoothQuant migration alpha=0.85 from rollout calibration statistics" in report.result.format
    assert report.to_header()["quant_report"]["act_calib"]["alpha"] == 0.85
    with pytest.raises(UserError, match="'smoothquant' smooths by definition"):
        config = QuantConfig.from_preset("W8A8", scope="llm", method="smoothquant")
        quantize_(_llama(), config, config.select(_llama(), COMPONENTS))


def test_preset_must_match_the_method():
    with pytest.raises(UserError, match="implements W8A8"):
        config = QuantConfig.from_preset("W4", scope="llm", method="smoothquant")
        quantize_(_llama(), config, config.select(_llama(), COMPONENTS))


@pytest.mark.skipif(importlib.util.find_spec("bitsandbytes") is not None, reason="bitsandbytes installed")
def test_bitsandbytes_methods_name_the_missing_extra():
    with pytest.raises(UserError, match=r"vlaquantbench\[kernels\]"):
        config = QuantConfig.from_preset("W4", scope="llm", method="nf4")
        quantize_(_llama(), config, config.select(_llama(), COMPONENTS))


@pytest.mark.parametrize("method", ["smoothquant", "fp8_tensor"])
def test_compiled_layers_share_one_graph_and_match_eager(method):
    """Each decoder layer compiled by inductor: the activation quantization is traced into the layer's
    graph (no graph break), both layers reuse that graph (no recompilation per layer), and the fused
    code computes what eager does (float32 model: 1e-5 relative)."""
    model = _llama(width=256)
    x = torch.randn(1, 32, 256, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        unquantized = model(inputs_embeds=x, use_cache=False).last_hidden_state
        config = _w8a8(method, model, x)
        report = quantize_(model, config, config.select(model, COMPONENTS))
        eager = model(inputs_embeds=x, use_cache=False).last_hidden_state
        assert report.unfired() == []
        for hook in report.result.hooks.values():  # dynamo would guard on their call counters
            hook.remove()
        torch._dynamo.reset()
        counters.clear()
        for layer in model.layers:
            layer.compile()
        compiled = model(inputs_embeds=x, use_cache=False).last_hidden_state
    assert counters["stats"]["unique_graphs"] == 1
    assert sum(counters["graph_break"].values()) == 0
    assert _rel(compiled, eager) < 1e-5
    assert _rel(compiled, unquantized) > 1e-3  # still quantized
    torch._dynamo.reset()


def _observed(model, x):
    layers = {n: m for n, m in model.named_modules() if isinstance(m, torch.nn.Linear)}
    with observe(layers, quantile=None) as observer, torch.no_grad():
        model(inputs_embeds=x)
    return observer.stats("test", {})


def test_static_fp8_uses_the_calibrated_input_range():
    model = _llama()
    x = torch.randn(1, 20, 64, generator=torch.Generator().manual_seed(1))
    stats = _observed(model, x)
    with torch.no_grad():
        reference = model(inputs_embeds=x).last_hidden_state
        cfg = QuantConfig.from_preset("W8A8", scope="llm", method="fp8_static", stats=stats)
        report = quantize_(model, cfg, cfg.select(model, COMPONENTS))
        out = model(inputs_embeds=x).last_hidden_state
    assert report.unfired() == [] and report.result.calibrated == set(report.selected)
    q_proj = model.layers[0].self_attn.q_proj
    expected = stats.layers["layers.0.self_attn.q_proj"].absmax.max() / FP8_MAX
    assert q_proj.input_scale.item() == pytest.approx(expected.item())
    assert 0 < _rel(out, reference) < 0.1


def test_static_fp8_equals_dynamic_at_the_calibrated_range_and_saturates_beyond():
    linear = torch.nn.Linear(64, 32)
    x = torch.randn(10, 64)
    static = Fp8StaticLinear(linear, x.abs().amax(dim=0))
    dynamic = Fp8DynamicLinear(linear, tensorwise=True)
    with torch.no_grad():
        assert torch.equal(static(x), dynamic(x))
        assert torch.isfinite(static(10 * x)).all()  # clamped at the e4m3 maximum, not cast to NaN


def test_static_fp8_needs_calibration_statistics():
    with pytest.raises(UserError, match="'fp8_static' needs calibration statistics"):
        config = QuantConfig.from_preset("W8A8", scope="llm", method="fp8_static")
        quantize_(_llama(), config, config.select(_llama(), COMPONENTS))
