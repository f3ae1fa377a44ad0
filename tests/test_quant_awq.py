"""AWQ (vlaquantbench.quant.awq + the `awq` method of quant.kernels) on real modules: a small
`transformers` LlamaModel with outlier input channels, and the LLM scope of the demo pi0.5."""

import copy

import pytest
import torch
from transformers import LlamaConfig, LlamaModel

from vlaquantbench.errors import UserError
from vlaquantbench.models import get_model_spec
from vlaquantbench.models.registry import Component
from vlaquantbench.quant import (
    CalibrationSettings,
    QuantConfig,
    quantize_,
    select_layers,
)
from vlaquantbench.quant import calibration as calib
from vlaquantbench.quant.awq import (
    ALPHAS,
    awq_scales,
    scaled_quant_error,
    search_scales,
)
from vlaquantbench.quant.grid import fake_quant_weight

COMPONENTS = {"llm": Component(roots=("layers",))}
HIDDEN = 256
OUTLIERS = torch.tensor([3, 40, 77, 130, 201, 250])


def _llama():
    """A real LLaMA decoder (random weights) whose RMSNorm gains make six input channels of every
    attention and MLP input ~20x larger than the rest, as in trained LLMs."""
    torch.manual_seed(0)
    config = LlamaConfig(hidden_size=HIDDEN, intermediate_size=512, num_hidden_layers=2, num_attention_heads=4,
                         num_key_value_heads=4, vocab_size=100)
    model = LlamaModel(config).eval()
    with torch.no_grad():
        for layer in model.layers:
            layer.input_layernorm.weight[OUTLIERS] = 20.0
            layer.post_attention_layernorm.weight[OUTLIERS] = 20.0
    return model


def _embeds(seed, tokens=64):
    return torch.randn(1, tokens, HIDDEN, generator=torch.Generator().manual_seed(seed))


def _awq_stats(model, seeds=(0, 1, 2, 3)):
    layers = select_layers(model, COMPONENTS, "llm").flat()
    with torch.no_grad(), calib.observe(layers, quantile=None, sample_rows=128) as observer:
        for seed in seeds:
            model(inputs_embeds=_embeds(seed))
    return observer.stats("awqtest00000", {"seed": 0})


def _rel(a, b):
    return ((a - b).norm() / b.norm()).item()


@pytest.fixture(scope="module")
def llama_and_stats():
    model = _llama()
    return model, _awq_stats(model)


def test_awq_beats_rtn_w4_on_held_out_inputs(llama_and_stats):
    model, stats = llama_and_stats
    held_out = _embeds(100, tokens=128)
    with torch.no_grad():
        reference = model(inputs_embeds=held_out).last_hidden_state
        outputs = {}
        for method in ("rtn", "awq"):
            quantized = copy.deepcopy(model)
            config = QuantConfig.from_preset("W4", scope="llm", method=method, stats=stats)
            report = quantize_(quantized, config, config.select(quantized, COMPONENTS))
            outputs[method] = quantized(inputs_embeds=held_out).last_hidden_state
    errors = {method: _rel(out, reference) for method, out in outputs.items()}
    print(f"held-out relative output error: AWQ {errors['awq']:.4f}, RTN W4 {errors['rtn']:.4f}, "
          f"ratio {errors['awq'] / errors['rtn']:.3f}")
    assert 0 < errors["awq"] < 0.8 * errors["rtn"]
    assert report.unfired() == []
    awq = report.to_header()["quant_report"]["awq"]
    assert awq["format"] == "awq-int4-g128" and sum(awq["alpha_histogram"].values()) == 14
    assert awq["alpha_mean"] > 0 and awq["calibration_rows"] == {"min": 128, "max": 128}


def test_layer_search_lowers_held_out_error_of_an_outlier_layer(llama_and_stats):
    model, stats = llama_and_stats
    name = "layers.0.mlp.gate_proj"
    layer = dict(model.named_modules())[name]
    search = search_scales(layer.weight, stats.layers[name].absmean, stats.layers[name].samples, 4, 128)
    assert search.alpha > 0 and search.error < search.rtn_error
    with calib.observe({name: layer}, quantile=None, sample_rows=256) as observer, torch.no_grad():
        model(inputs_embeds=_embeds(100, tokens=256))
    rows = observer.layers[name].samples  # held-out inputs of this layer
    awq = scaled_quant_error(layer.weight, search.scales, rows, 4, 128, False)
    rtn = scaled_quant_error(layer.weight, torch.ones(HIDDEN), rows, 4, 128, False)
    print(f"{name} held-out squared output error: AWQ/RTN {awq / rtn:.3f} at alpha {search.alpha}")
    assert awq < 0.8 * rtn


def test_alpha_zero_is_plain_rtn_exactly(llama_and_stats):
    model, stats = llama_and_stats
    name = "layers.1.self_attn.q_proj"
    weight, layer_stats = model.layers[1].self_attn.q_proj.weight, stats.layers[name]
    ones = awq_scales(layer_stats.absmean, 0.0)
    assert torch.equal(ones, torch.ones(HIDDEN))
    assert torch.equal(fake_quant_weight(weight * ones, 4, 128, False), fake_quant_weight(weight, 4, 128, False))
    only_zero = search_scales(weight, layer_stats.absmean, layer_stats.samples, 4, 128, alphas=(0.0,))
    x = layer_stats.samples
    rtn = (x @ fake_quant_weight(weight, 4, 128, False).t() - x @ weight.t()).pow(2).sum().item()
    assert only_zero.alpha == 0.0 and only_zero.error == only_zero.rtn_error == rtn


def test_search_and_sampling_are_deterministic(llama_and_stats):
    model, stats = llama_and_stats
    again = _awq_stats(_llama())
    name = "layers.1.mlp.down_proj"
    assert torch.equal(stats.layers[name].samples, again.layers[name].samples)
    weight = model.layers[1].mlp.down_proj.weight
    first = search_scales(weight, stats.layers[name].absmean, stats.layers[name].samples, 4, 128)
    second = search_scales(weight, again.layers[name].absmean, again.layers[name].samples, 4, 128)
    assert first.alpha == second.alpha and first.alpha in ALPHAS and torch.equal(first.scales, second.scales)


def test_strided_sample_depends_on_stream_position_not_call_sizes():
    rows = torch.arange(180.0).reshape(180, 1)
    split = None, 1
    seen = 0
    for size in (50, 30, 100):
        split = calib.keep_strided_rows(split[0], split[1], seen, rows[seen:seen + size], limit=16)
        seen += size
    whole = calib.keep_strided_rows(None, 1, 0, rows, limit=16)
    assert split[1] == whole[1] == 16  # 180 rows at stride 8 would be 23 > 16
    assert torch.equal(split[0], whole[0]) and torch.equal(whole[0], rows[::16])


def test_absmean_is_the_mean_over_every_row():
    layer = torch.nn.Linear(3, 2)
    calls = [torch.randn(7, 3), torch.randn(2, 5, 3)]
    with calib.observe({"l": layer}, quantile=None, sample_rows=4) as observer:
        for x in calls:
            layer(x)
    stats = observer.layers["l"]
    every_row = torch.cat([x.reshape(-1, 3) for x in calls])
    assert stats.rows == 17 and stats.samples.shape[0] <= 4
    assert torch.allclose(stats.absmean, every_row.abs().mean(dim=0))


def test_scales_divide_out_exactly_without_quantization(llama_and_stats):
    model, stats = llama_and_stats
    name = "layers.0.mlp.down_proj"
    layer = model.layers[0].mlp.down_proj
    search = search_scales(layer.weight, stats.layers[name].absmean, stats.layers[name].samples, 4, 128)
    assert search.alpha > 0 and not torch.allclose(search.scales, torch.ones_like(search.scales))
    scaled = copy.deepcopy(layer)
    with torch.no_grad():
        scaled.weight.mul_(search.scales)
        x = stats.layers[name].samples
        assert _rel(scaled(x / search.scales), layer(x)) <= 1e-5


def test_missing_awq_statistics_fail_before_the_model_changes():
    model = _llama()
    before = {k: v.clone() for k, v in model.state_dict().items()}
    with pytest.raises(UserError, match=r"method 'awq'.*observe\(layers, sample_rows=128\)"):
        config = QuantConfig.from_preset("W4", scope="llm", method="awq")
        quantize_(model, config, config.select(model, COMPONENTS))
    layers = select_layers(model, COMPONENTS, "llm").flat()
    with torch.no_grad(), calib.observe(layers, quantile=None) as observer:  # smoothing statistics only
        model(inputs_embeds=_embeds(0))
    smoothing_only = observer.stats("k", {})
    with pytest.raises(UserError, match="14 selected layers, e.g. layers.0.self_attn.q_proj"):
        config = QuantConfig.from_preset("W4", scope="llm", method="awq", stats=smoothing_only)
        quantize_(model, config, config.select(model, COMPONENTS))
    with pytest.raises(UserError, match="weight-only"):
        config = QuantConfig.from_preset("W4A8", scope="llm", method="awq", stats=smoothing_only)
        quantize_(model, config, config.select(model, COMPONENTS))
    assert all(torch.equal(before[k], v) for k, v in model.state_dict().items())


def test_awq_statistics_are_opt_in_for_the_cache_key_and_survive_save_load(tmp_path, llama_and_stats):
    _, stats = llama_and_stats
    fields = {"model": "pi05", "checkpoint": "c", "revision": "r", "init_states": [20, 21], "tasks": 1, "seed": 0,
              "settings": CalibrationSettings(), "code_revision": "x"}
    assert "sample_rows" not in calib.keyed_fields(*fields.values())  # existing caches keep their keys
    awq_fields = {**fields, "settings": CalibrationSettings(alpha=None, quantile=None, sample_rows=128)}
    assert calib.keyed_fields(*awq_fields.values())["sample_rows"] == 128
    assert calib.calibration_key(**awq_fields) != calib.calibration_key(**fields)
    loaded = calib.load_stats(calib.save_stats(stats, tmp_path / "awq.pt"))
    for name, layer in stats.layers.items():
        got = loaded.layers[name]
        assert torch.equal(got.samples, layer.samples) and torch.equal(got.absmean, layer.absmean)
        assert (got.rows, got.sample_stride, got.calls) == (layer.rows, layer.sample_stride, layer.calls)


def test_awq_on_the_llm_scope_of_demo_pi05():
    spec = get_model_spec("pi05")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        policy = spec.build("demo", device="cpu", seed=0)

        def sample(seed):
            g = torch.Generator().manual_seed(seed)
            images, masks = [torch.rand(1, 3, 224, 224, generator=g) * 2 - 1], [torch.ones(1, dtype=torch.bool)]
            tokens = torch.randint(0, 257152, (1, 16), generator=g)
            noise = torch.randn(1, 50, 32, generator=g)
            return policy.sample_actions(images, masks, tokens, torch.ones(1, 16, dtype=torch.bool), noise=noise,
                                         num_steps=1)

        layers = select_layers(policy, spec.components, "llm").flat()
        with torch.no_grad(), calib.observe(layers, quantile=None, sample_rows=128) as observer:
            for seed in (0, 1):
                sample(seed)
        stats = observer.stats("pi05awq00000", {"init_states": [20, 21]})
        with torch.no_grad():
            reference = sample(5)
            config = QuantConfig.from_preset("W4", scope="llm", method="awq", stats=stats)
            report = quantize_(policy, config, config.select(policy, spec.components))
            assert report.unfired() == list(layers)  # hooks installed on all 126, none run yet
            actions = sample(5)
    finally:
        torch.set_num_threads(threads)
    assert report.unfired() == []
    header = report.to_header()
    assert header["hooks"] == {"selected": 126, "fired": 126, "unfired": []}
    assert header["quant_report"]["llm"]["layers"] == 126
    assert header["quant_format"].startswith("awq-int4-g128")
    assert sum(header["quant_report"]["awq"]["alpha_histogram"].values()) == 126
    assert torch.isfinite(actions).all() and not torch.equal(actions, reference)
