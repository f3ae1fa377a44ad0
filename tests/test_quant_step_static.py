"""Per-denoising-step activation scales (`quant.steps`, `quant.step_static`) on the demo pi0.5, pi0 and
X-VLA (real lerobot architectures, random weights): the adapters' flow-step clock, per-step statistics
from the calibration observer, and a `step_static` quantization whose activations sit on the grid of
the step that ran."""

import copy

import pytest
import torch
from pi_chunks import pi_chunk
from test_runner_adapter import observations

from vlaquantbench.models import get_model_spec
from vlaquantbench.models.adapter import AdapterConfig, make_adapter
from vlaquantbench.quant import QuantConfig, quantize_, select_layers
from vlaquantbench.quant import calibration as calib
from vlaquantbench.quant.step_static import static_grid
from vlaquantbench.quant.steps import attach_flow_clock, flow_clock
from vlaquantbench.replay.probe import PolicyProbe

FLOW_STEPS = 3


@pytest.mark.parametrize("model_name", ["pi05", "pi0", "xvla"])
def test_the_adapters_clock_counts_the_configured_flow_steps_per_chunk(model_name):
    """Action-head layers run once per flow step, whatever the batch; the other components (the
    prefix/KV pass, the vision tower) run outside steps, once per chunk."""
    adapter = make_adapter(AdapterConfig(model=model_name, variant="demo", flow_steps=FLOW_STEPS))
    adapter.load()
    clock = flow_clock(adapter.model)
    head = next(iter(select_layers(adapter.model, adapter.components, "ah").flat().items()))
    vision = next(iter(select_layers(adapter.model, adapter.components, "ve").flat().items()))
    seen = {head[0]: [], vision[0]: []}
    for name, layer in (head, vision):
        layer.register_forward_pre_hook(lambda module, args, name=name: seen[name].append(clock.step))
    for batch in (1, 2):
        adapter.act(observations(batch, seed=batch), [adapter.reset(s) for s in range(batch)])
        assert clock.steps_in_chunk == FLOW_STEPS and clock.step is None
    assert seen[head[0]] == [*range(FLOW_STEPS)] * 2
    assert set(seen[vision[0]]) == {None}


@pytest.fixture(scope="module")
def calibrated():
    """The demo pi0.5 with its adapter's clock and the step scales of its action head, observed on two
    unquantized chunks of lerobot's `sample_actions`."""
    spec = get_model_spec("pi05")
    model = spec.build("demo", device="cpu", seed=0)
    clock = attach_flow_clock(model, "sample_actions", "denoise_step")
    layers = select_layers(model, spec.components, "e2e").flat()
    with torch.no_grad(), calib.observe(layers, quantile=None, clock=clock) as observer:
        for seed in (0, 1):
            pi_chunk("pi05", model, seed, steps=FLOW_STEPS)
    return spec, model, observer.stats("steps", {"seed": 0})


def test_step_scales_are_kept_per_step_for_the_action_head_only(calibrated, tmp_path):
    spec, model, stats = calibrated
    head = set(select_layers(model, spec.components, "ah").flat())
    stepped = {n for n, s in stats.layers.items() if s.step_absmax is not None}
    assert stepped == head and len(head) == 167
    varying = 0
    for name in head:
        steps = stats.layers[name].step_absmax
        assert steps.shape == (FLOW_STEPS,) and torch.all(steps > 0)
        assert steps.max() == pytest.approx(stats.layers[name].absmax.max().item())
        varying += bool((steps.max() - steps.min()) > 0.05 * steps.max())
    print(f"{varying} of {len(head)} action-head layers: step absmax range over 5% of its max")
    assert varying > len(head) // 2  # the flow time changes what the head sees
    loaded = calib.load_stats(calib.save_stats(stats, tmp_path / "stats.pt"))
    assert all(torch.equal(loaded.layers[n].step_absmax, stats.layers[n].step_absmax) for n in head)


def test_step_static_quantizes_each_step_on_that_steps_grid(calibrated):
    spec, demo, stats = calibrated
    policy = copy.deepcopy(demo)  # a copy with its own clock
    clock = flow_clock(policy)
    assert clock is not flow_clock(demo)
    config = QuantConfig.from_preset("W4A8", scope="e2e", method="step_static", stats=stats)
    report = quantize_(policy, config, config.select(policy, spec.components))
    name = "paligemma_with_expert.gemma_expert.model.layers.3.mlp.down_proj"
    layer, steps = policy.get_submodule(name), stats.layers[name].step_absmax
    raw, quantized = [], []
    layer.register_forward_pre_hook(lambda m, args: raw.append((clock.step, args[0].clone())), prepend=True)
    layer.register_forward_pre_hook(lambda m, args: quantized.append(args[0].clone()))  # after the quantizer
    llm = "paligemma_with_expert.paligemma.model.language_model.layers.0.mlp.down_proj"
    with torch.no_grad():
        actions = pi_chunk("pi05", policy, 5, steps=FLOW_STEPS)
    header = report.to_header()
    assert header["hooks"] == {"selected": 456, "fired": 456, "unfired": []}
    assert header["quant_report"]["step_static"] == {"per_step_layers": 167, "per_layer_layers": 289,
                                                     "flow_steps": FLOW_STEPS}
    assert header["quant_format"].startswith("RTN weights 4-bit asymmetric, group 128; activations 8-bit symmetric, "
                                             "static per-tensor scales per flow step")
    assert [step for step, _ in raw] == [*range(FLOW_STEPS)] and torch.isfinite(actions).all()
    for (step, x), got in zip(raw, quantized):
        grid = static_grid(steps[step], 8)
        assert torch.equal(got, grid.quantize(x))  # the grid of the step that ran ...
        codes = got / grid.scale
        assert torch.allclose(codes, codes.round(), atol=1e-3) and codes.abs().max() <= 128
        other = static_grid(steps[(step + 1) % FLOW_STEPS], 8)
        assert not torch.equal(got, other.quantize(x))  # ... and not another step's
    outside = report.result.hooks[llm].transform  # a prefix-pass layer: its one per-layer grid
    assert outside.step_grids == () and outside.layer_grid.scale == stats.layers[llm].absmax.max() / 127


def test_a_step_the_calibration_never_saw_is_an_error_naming_the_layer(calibrated):
    spec, demo, stats = calibrated
    policy = copy.deepcopy(demo)
    config = QuantConfig.from_preset("W8A8", scope="ah", method="step_static", stats=stats)
    quantize_(policy, config, config.select(policy, spec.components))
    with torch.no_grad(), pytest.raises(RuntimeError, match=r"action_in_proj: flow step 3 is running, but the "
                                                            r"calibration saw 3 steps"):
        pi_chunk("pi05", policy, 0, steps=FLOW_STEPS + 1)


def test_the_replay_probe_leaves_the_clock_in_place(calibrated):
    _, demo, _ = calibrated
    policy = copy.deepcopy(demo)
    with PolicyProbe(policy, ["*gemma_expert*down_proj"], action_dims=7) as probe, probe.call():
        pi_chunk("pi05", policy, 0, steps=FLOW_STEPS)
    assert len(probe.states) == FLOW_STEPS
    pi_chunk("pi05", policy, 0, steps=2)
    assert flow_clock(policy).steps_in_chunk == 2  # still advanced by the model's own denoise steps
