"""quantize_ on the real lerobot pi0.5 architecture (demo widths, random weights): weight rounding,
hook accounting, rollout calibration, and the errors raised before anything changes."""

import copy
import dataclasses

import pytest
import torch
from torch import nn

from vlaquantbench.errors import UserError
from vlaquantbench.models import get_model_spec
from vlaquantbench.quant import (
    CalibrationSettings,
    HooksNotFired,
    MethodResult,
    QuantConfig,
    quantize_,
    register_method,
    select_layers,
)
from vlaquantbench.quant import calibration as calib
from vlaquantbench.quant.grid import fake_quant_weight
from vlaquantbench.quant.presets import FORMATS

SPEC = get_model_spec("pi05")


@pytest.fixture(scope="module")
def demo():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # small matrices: one thread is as fast and immune to a busy machine
    yield SPEC.build("demo", device="cpu", seed=0)
    torch.set_num_threads(threads)


@pytest.fixture
def policy(demo):
    return copy.deepcopy(demo)


def chunk_inputs(seed=0):
    g = torch.Generator().manual_seed(seed)
    images = [torch.rand(1, 3, 224, 224, generator=g) * 2 - 1]  # one camera keeps the tests quick
    masks = [torch.ones(1, dtype=torch.bool)]
    tokens = torch.randint(0, 257152, (1, 16), generator=g)
    return images, masks, tokens, torch.ones(1, 16, dtype=torch.bool), torch.randn(1, 50, 32, generator=g)


def sample(model, steps=1):
    images, masks, tokens, token_masks, noise = chunk_inputs()
    return model.sample_actions(images, masks, tokens, token_masks, noise=noise, num_steps=steps)


def test_demo_is_the_real_architecture_with_seeded_weights(demo):
    assert type(demo).__name__ == "PI05Pytorch"
    again = SPEC.build("demo", device="cpu", seed=0)
    other = SPEC.build("demo", device="cpu", seed=1)
    w = "paligemma_with_expert.gemma_expert.model.layers.3.mlp.down_proj.weight"
    assert torch.equal(demo.state_dict()[w], again.state_dict()[w])
    assert not torch.equal(demo.state_dict()[w], other.state_dict()[w])
    counts = select_layers(demo, SPEC.components, "e2e").counts()
    assert {c: v["layers"] for c, v in counts.items()} == {"ve": 162, "mp": 1, "llm": 126, "ah": 167}


def test_pi0_demo_runs_its_real_architecture():
    spec = get_model_spec("pi0")
    model = spec.build("demo", device="cpu", seed=0)
    assert type(model).__name__ == "PI0Pytorch"
    assert select_layers(model, spec.components, "ah").counts()["ah"]["layers"] == 131
    images, masks, tokens, token_masks, noise = chunk_inputs()
    state = torch.zeros(1, 32)
    first = model.sample_actions(images, masks, tokens, token_masks, state, noise=noise, num_steps=1)
    again = model.sample_actions(images, masks, tokens, token_masks, state, noise=noise, num_steps=1)
    assert first.shape == (1, 50, 32) and torch.isfinite(first).all() and torch.equal(first, again)


def test_weights_rounded_in_place_only_where_selected(policy):
    name = "paligemma_with_expert.gemma_expert.model.layers.0.self_attn.q_proj"
    untouched = "paligemma_with_expert.gemma_expert.model.layers.0.mlp.up_proj"
    modules = dict(policy.named_modules())
    before, before_other = modules[name].weight.clone(), modules[untouched].weight.clone()
    config = QuantConfig.from_preset("W4", scope="ah", only=["*self_attn*"])
    report = quantize_(policy, config, config.select(policy, SPEC.components))
    assert report.components == {"ah": {"layers": 72, "params": sum(
        modules[n].weight.numel() for n in report.selected)}}
    assert torch.equal(modules[name].weight, fake_quant_weight(before, 4, 128, symmetric=False))
    assert torch.equal(modules[untouched].weight, before_other)
    assert report.to_header()["hooks"] == {"selected": 0, "fired": 0, "unfired": []}  # weight-only


def test_hook_accounting_names_exactly_the_skipped_layers(policy):
    config = QuantConfig.from_preset("W4A4", scope="e2e")
    report = quantize_(policy, config, config.select(policy, SPEC.components))
    groups = report.selection.layers
    images, *_ = chunk_inputs()
    policy.paligemma_with_expert.embed_image(images[0])  # runs only the vision tower and projector
    assert set(report.unfired()) == set(groups["llm"]) | set(groups["ah"])
    assert all(report.hook_calls()[n] == 1 for n in [*groups["ve"], *groups["mp"]])
    with pytest.raises(HooksNotFired, match="paligemma_with_expert.gemma_expert.model.layers.17.mlp.down_proj"):
        report.check_hooks_fired()

    report.reset_hook_calls()
    sample(policy, steps=2)
    assert report.unfired() == []
    report.check_hooks_fired()
    expert_calls = report.hook_calls()["paligemma_with_expert.gemma_expert.model.layers.0.self_attn.q_proj"]
    assert expert_calls == 2  # once per flow step
    header = report.to_header()
    assert header["hooks"] == {"selected": 456, "fired": 456, "unfired": []}
    assert header["quant_report"]["ah"]["layers"] == 167 and len(header["selected_layers"]) == 456


def test_activation_quantization_changes_actions_and_baseline_does_not(demo, policy):
    reference = sample(demo)
    config = QuantConfig.from_preset("BASELINE")
    base_report = quantize_(policy, config, config.select(policy, SPEC.components))
    assert torch.equal(sample(policy), reference)
    assert base_report.to_header()["quant_report"]["ah"] == {"layers": 0, "params": 0, "mean_rel_mse": None}
    config = QuantConfig.from_preset("W4A4", scope="ah")
    quantize_(policy, config, config.select(policy, SPEC.components))
    assert not torch.allclose(sample(policy), reference, atol=1e-3)


@pytest.mark.parametrize("preset", ["MXFP4", "NVFP4", "FP8E4M3"])
def test_float_format_presets_quantize_weights_and_inputs_through_counted_hooks(policy, preset):
    fmt = FORMATS[preset]
    name = "paligemma_with_expert.gemma_expert.model.layers.2.mlp.down_proj"
    layer = dict(policy.named_modules())[name]
    before = layer.weight.clone()
    config = QuantConfig.from_preset(preset, scope="ah")
    report = quantize_(policy, config, config.select(policy, SPEC.components))
    assert torch.equal(layer.weight, fmt.quantize_weight(before)) and not torch.equal(layer.weight, before)
    seen = {}

    def record(module, args):  # runs after the counting hook: sees the input the layer multiplies
        seen["x"] = args[0]

    raw = {}
    layer.register_forward_pre_hook(lambda module, args: raw.setdefault("x", args[0].clone()), prepend=True)
    layer.register_forward_pre_hook(record)
    sample(policy)
    report.check_hooks_fired()
    assert torch.equal(seen["x"], fmt.quantize_activation(raw["x"])) and not torch.equal(seen["x"], raw["x"])
    header = report.to_header()
    assert header["hooks"] == {"selected": 167, "fired": 167, "unfired": []}
    assert header["quant_format"].startswith(f"RTN weights {preset}:") and f"activations {preset}:" in header["quant_format"]


def test_bad_scope_and_patterns_fail_before_any_change(policy):
    snapshot = {k: v.clone() for k, v in policy.state_dict().items() if "vision_tower.encoder.layers.0" in k}
    with pytest.raises(UserError, match=r"'\*nothing_here\*'"):
        config = QuantConfig.from_preset("W4", scope="e2e", only=["*self_attn*", "*nothing_here*"])
        quantize_(policy, config, config.select(policy, SPEC.components))
    with pytest.raises(UserError, match=r"--exclude '\*nope'"):
        config = QuantConfig.from_preset("W4", scope="ve", exclude=["*nope"])
        quantize_(policy, config, config.select(policy, SPEC.components))
    with pytest.raises(UserError, match="unknown scope 'vision'"):
        config = QuantConfig.from_preset("W4", scope="vision")
        quantize_(policy, config, config.select(policy, SPEC.components))
    with pytest.raises(UserError, match="unknown quantization method 'obq'"):
        QuantConfig.from_preset("W4", method="obq")
    with pytest.raises(UserError, match=r"method 'gptq' needs GPTQ calibration statistics .* for 456 selected layers"):
        config = QuantConfig.from_preset("W4", method="gptq")
        quantize_(policy, config, config.select(policy, SPEC.components))
    for k, v in snapshot.items():
        assert torch.equal(policy.state_dict()[k], v)


def test_registered_method_receives_the_selection(policy):
    seen = {}

    def record(model, selection, config):
        seen.update(selection.counts())
        return MethodResult(format="recorded")

    register_method("test_record", record)
    config = QuantConfig.from_preset("W4", scope="llm", method="test_record")
    report = quantize_(policy, config, config.select(policy, SPEC.components))
    assert seen == report.components and seen["llm"]["layers"] == 126
    assert report.to_header()["quant_format"] == "recorded"


@pytest.fixture(scope="module")
def ah_stats(demo):
    """Statistics observed on every AH layer during one unquantized action chunk."""
    layers = select_layers(demo, SPEC.components, "ah").flat()
    with calib.observe(layers, 0.999) as observer:
        sample(demo)
    fields = dict(model="pi05", checkpoint="demo", revision=None, init_states=[20, 21], tasks=1, seed=0,
                  settings=CalibrationSettings(), code_revision="test")
    return observer.stats(calib.calibration_key(**fields), {"init_states": [20, 21], "tasks": 1, "seed": 0})


def test_smoothing_without_clip_or_quantization_preserves_each_linear_output(demo, policy, ah_stats):
    stats = ah_stats
    assert len(stats.layers) == 167
    smoothed = QuantConfig.from_preset("BASELINE", scope="ah", calibration=CalibrationSettings(quantile=None),
                                       stats=stats)
    report = quantize_(policy, smoothed, smoothed.select(policy, SPEC.components))
    assert report.to_header()["quant_report"]["ah"]["calibrated_layers"] == 167
    originals = dict(demo.named_modules())
    g = torch.Generator().manual_seed(3)
    for name, layer in report.selection.flat().items():
        ch = stats.layers[name].absmax
        x = torch.randn(4, ch.numel(), generator=g) * ch  # realistic per-channel ranges, outliers included
        want, got = originals[name](x), layer(x)
        rel = (got - want).norm() / want.norm()
        assert rel <= 1e-5, name
    assert not torch.equal(dict(policy.named_modules())[name].weight, originals[name].weight)


def test_calibrated_w4a4_records_provenance_and_clips(policy, ah_stats):
    stats = ah_stats
    settings = CalibrationSettings(alpha=0.5, quantile=0.999, components=("ah",))
    config = QuantConfig.from_preset("W4A4", scope="ah", calibration=settings, stats=stats)
    report = quantize_(policy, config, config.select(policy, SPEC.components))
    header = report.to_header()
    assert header["quant_report"]["ah"]["calibrated_layers"] == 167
    act = header["quant_report"]["act_calib"]
    assert act["components"] == ["ah"] and act["alpha"] == 0.5 and act["clip_quantile"] == 0.999
    assert act["cache"] == f"{stats.key}.pt" and act["init_states"] == [20, 21]
    hook = report.result.hooks["action_out_proj"]
    d = hook.transform.smooth
    expected_clip = (stats.layers["action_out_proj"].quantile / d).clamp_min(1e-5)
    assert torch.equal(hook.transform.clip, expected_clip)
    sample(policy)
    report.check_hooks_fired()


def test_observer_keeps_max_of_per_call_quantiles():
    layer = nn.Linear(3, 2)
    calls = [torch.randn(1000, 3, generator=torch.Generator().manual_seed(i)) * (i + 1) for i in range(3)]
    single = torch.tensor([[5.0, -7.0, 0.5]])
    with calib.observe({"l": layer}, 0.999) as observer:
        for x in calls:
            layer(x)
        layer(single)
    layer(single * 100)  # after the block: no longer observed
    stats = observer.layers["l"]
    per_call = torch.stack([torch.quantile(x.abs(), 0.999, dim=0) for x in calls] + [single.abs()[0]]).amax(0)
    pooled = torch.quantile(torch.cat(calls).abs(), 0.999, dim=0)
    assert torch.equal(stats.quantile, per_call) and not torch.equal(stats.quantile, pooled)
    assert torch.equal(stats.absmax, torch.cat([*calls, single]).abs().amax(0))
    assert stats.calls == 4


def test_huge_calls_are_sampled_at_a_fixed_stride(monkeypatch):
    monkeypatch.setattr(calib, "QUANTILE_MAX_ELEMENTS", 40)
    x = torch.arange(100 * 4, dtype=torch.float32).reshape(100, 4)  # 10 tokens fit: stride 10
    assert torch.equal(calib.per_call_quantile(x, 0.5), torch.quantile(x[::10], 0.5, dim=0))


BASE_KEY = dict(model="pi05", checkpoint="lerobot/pi05_libero_finetuned_v044", revision="8e17415",
                init_states=[20, 21], tasks=1, seed=0, settings=CalibrationSettings(), code_revision="abc")


@pytest.mark.parametrize("field, value", [
    ("revision", "45dcc8f"), ("init_states", [0, 1]), ("tasks", 2), ("seed", 1),
    ("settings", CalibrationSettings(alpha=0.75)), ("settings", CalibrationSettings(quantile=0.99)),
    ("code_revision", "def"), ("checkpoint", "lerobot/pi0_libero_finetuned_v044"),
])
def test_calibration_key_changes_with_each_field(field, value):
    assert calib.calibration_key(**{**BASE_KEY, field: value}) != calib.calibration_key(**BASE_KEY)
    assert calib.calibration_key(**BASE_KEY) == calib.calibration_key(**dict(BASE_KEY))


def test_stats_roundtrip_and_key_check(tmp_path):
    stats = calib.CalibrationStats("abc123abc123", {"seed": 0},
                                   {"l": calib.ChannelStats(torch.tensor([1.0, 2.0]), torch.tensor([0.5, 1.5]), 3)})
    path = calib.save_stats(stats, tmp_path / "cache" / "abc123abc123.pt")
    loaded = calib.load_stats(path, expected_key="abc123abc123")
    assert dataclasses.asdict(loaded).keys() == dataclasses.asdict(stats).keys()
    assert torch.equal(loaded.layers["l"].quantile, stats.layers["l"].quantile) and loaded.layers["l"].calls == 3
    with pytest.raises(UserError, match="expected ffffffffffff"):
        calib.load_stats(path, expected_key="ffffffffffff")
    with pytest.raises(UserError, match="not found"):
        calib.load_stats(tmp_path / "missing.pt")
