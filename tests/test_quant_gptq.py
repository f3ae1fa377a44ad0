"""GPTQ (vlaquantbench.quant.gptq) on the demo pi0.5 and pi0 (real lerobot architectures, random weights),
with Hessians collected by the rollout calibration's observer on real action chunks: against an
independent column-by-column implementation of the published algorithm, against RTN on every layer,
and through `quantize_` (header, hooks, mean_rel_mse)."""

import copy

import pytest
import torch
from gptq_errors import gptq_against_rtn, output_error
from pi_chunks import pi_chunk

from vlaquantbench.errors import UserError
from vlaquantbench.models import get_model_spec
from vlaquantbench.quant import QuantConfig, quantize_, select_layers
from vlaquantbench.quant import calibration as calib
from vlaquantbench.quant.gptq import gptq_weight
from vlaquantbench.quant.presets import parse_preset

MODELS = ("pi05", "pi0")


@pytest.fixture(scope="module")
def calibrated():
    """Per model: the demo policy and GPTQ statistics (Hessians and sampled rows) of every e2e layer,
    observed on two unquantized action chunks."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    built = {}
    for name in MODELS:
        spec = get_model_spec(name)
        model = spec.build("demo", device="cpu", seed=0)
        layers = select_layers(model, spec.components, "e2e").flat()
        with torch.no_grad(), calib.observe(layers, quantile=None, sample_rows=128, hessian=True) as observer:
            for seed in (0, 1):
                pi_chunk(name, model, seed)
        built[name] = (spec, model, observer.stats(f"gptq{name}", {"seed": 0}))
    yield built
    torch.set_num_threads(threads)


def _reference_grid(columns, bits):
    """The asymmetric min-max grid of each row (zero included), float32, as the paper's W4 preset."""
    levels = 2**bits - 1
    low = columns.float().amin(dim=1, keepdim=True).clamp_max(0.0)
    high = columns.float().amax(dim=1, keepdim=True).clamp_min(0.0)
    scale = ((high - low) / levels).clamp_min(1e-8)
    zero = torch.round(-low / scale).clamp(0, levels)
    return lambda w: (torch.clamp(torch.round(w.float()[:, None] / scale) + zero, 0, levels) - zero)[:, 0] * scale[:, 0]


def reference_gptq(weight, hessian, bits, group, damp, act_order):
    """GPTQ as the paper's optimal-brain-surgeon form states it, one column at a time and without
    Cholesky factors or lazy batches: round column j, move every remaining column k by
    -(w_j - q_j) / [H^-1]_jj * [H^-1]_jk, then eliminate j from H^-1 (H^-1 -= H^-1_:j H^-1_j: / H^-1_jj).
    Dead inputs zeroed, damping `damp` * mean diagonal; a group's grid fixed at its first rounded column
    from its current weights, or up front from the original weights with `act_order`."""
    w = weight.double().clone()
    h = hessian.double().clone()
    dead = h.diagonal() == 0
    h[dead, dead] = 1.0
    w[:, dead] = 0.0
    h += damp * h.diagonal().mean() * torch.eye(h.shape[0], dtype=torch.float64)
    inverse = torch.linalg.inv(h)
    n = w.shape[1]
    order = torch.argsort(h.diagonal(), descending=True, stable=True).tolist() if act_order else range(n)
    grids = {g: _reference_grid(w[:, g * group:(g + 1) * group], bits) for g in range(-(-n // group))} if act_order else {}
    q = torch.empty_like(w)
    for j in order:
        if j // group not in grids:
            grids[j // group] = _reference_grid(w[:, j // group * group:(j // group + 1) * group], bits)
        q[:, j] = grids[j // group](w[:, j]).double()
        w -= ((w[:, j] - q[:, j]) / inverse[j, j])[:, None] * inverse[j][None, :]
        inverse -= inverse[:, j:j + 1] @ inverse[j:j + 1, :] / inverse[j, j]
    return q


@pytest.mark.parametrize("act_order", [False, True])
def test_agrees_with_a_column_by_column_reference(calibrated, act_order):
    _, model, stats = calibrated["pi05"]
    name = "paligemma_with_expert.paligemma.model.language_model.layers.0.mlp.down_proj"  # groups of 96, 96 and 64
    weight, hessian = model.get_submodule(name).weight.detach(), stats.layers[name].hessian
    grid = parse_preset("W4G96").weight
    ours = gptq_weight(weight, hessian, grid, damp=0.01, act_order=act_order, block_size=32)
    reference = reference_gptq(weight, hessian, 4, 96, 0.01, act_order)
    same = (ours.weight.double() == reference).float().mean().item()
    errors = output_error(weight, ours.weight, hessian), output_error(weight, reference, hessian)
    print(f"{name} act_order={act_order}: {same:.5f} of weights identical; output error {errors[0]:.4g} vs "
          f"reference {errors[1]:.4g}, RTN {ours.rtn_error:.4g}")
    assert weight.shape[1] == 256 and same >= 0.999
    assert abs(errors[0] - errors[1]) <= 1e-3 * errors[1] and ours.error == pytest.approx(errors[0], rel=1e-9)


def test_identity_hessian_gives_rtn_weights_exactly(calibrated):
    _, model, _ = calibrated["pi05"]
    weight = model.get_submodule("paligemma_with_expert.paligemma.model.language_model.layers.0.mlp.down_proj").weight
    for preset in ("W4", "W3G64SYM", "W8", "W4G0"):
        grid = parse_preset(preset).weight
        got = gptq_weight(weight, torch.eye(weight.shape[1]), grid).weight
        assert torch.equal(got, grid.quantize_weight(weight.float())), preset


@pytest.mark.parametrize("model_name", MODELS)
def test_gptq_error_at_most_rtn_on_every_layer(calibrated, model_name):
    """On the calibration inputs (all observed rows, through X^T X), every e2e layer's output error."""
    spec, model, stats = calibrated[model_name]
    ratios, worse = gptq_against_rtn(select_layers(model, spec.components, "e2e").flat(), stats, ("W4", "W3G0"))
    print(f"{model_name}: {len(ratios)} layer grids, GPTQ/RTN error mean {sum(ratios) / len(ratios):.3f}, "
          f"max {max(ratios):.3f}")
    assert worse == [] and sum(ratios) / len(ratios) < 0.9


def test_quantize_gptq_w4a8_on_e2e(calibrated):
    spec, demo, stats = calibrated["pi05"]
    policy = copy.deepcopy(demo)
    with torch.no_grad():
        config = QuantConfig.from_preset("W4A8", scope="e2e", method="gptq", stats=stats)
        report = quantize_(policy, config, config.select(policy, spec.components))
        assert report.unfired() == list(report.selection.flat())  # reporting mean_rel_mse counted no call
        actions = pi_chunk("pi05", policy, 5)
        rtn_policy = copy.deepcopy(demo)
        rtn_config = QuantConfig.from_preset("W4A8", scope="e2e", stats=stats)
        rtn_report = quantize_(rtn_policy, rtn_config, rtn_config.select(rtn_policy, spec.components))
    header = report.to_header()
    assert header["hooks"] == {"selected": 456, "fired": 456, "unfired": []}
    assert header["quant_format"].startswith("GPTQ weights 4-bit asymmetric, group 128; activations 8-bit")
    details = header["quant_report"]["gptq"]
    assert details["error_vs_rtn_max"] <= 1.0 and details["act_order"] is False and details["damp"] == 0.01
    for comp in ("ve", "mp", "llm", "ah"):
        got, rtn = header["quant_report"][comp]["mean_rel_mse"], rtn_report.to_header()["quant_report"][comp]["mean_rel_mse"]
        print(f"{comp}: mean_rel_mse GPTQ {got:.4g}, RTN {rtn:.4g}")
        assert 0 < got < rtn
    assert torch.isfinite(actions).all()


def test_mean_rel_mse_is_the_relative_output_error_on_the_sampled_rows(calibrated):
    spec, demo, stats = calibrated["pi0"]
    policy = copy.deepcopy(demo)
    config = QuantConfig.from_preset("W4A4", scope="ah", stats=stats)
    report = quantize_(policy, config, config.select(policy, spec.components))
    errors = []
    with torch.no_grad():
        for name, layer in report.selection.flat().items():
            rows = stats.layers[name].samples
            want = demo.get_submodule(name)(rows)
            got = torch.nn.functional.linear(report.result.hooks[name].transform(rows), layer.weight, layer.bias)
            errors.append(((got - want).pow(2).sum() / want.pow(2).sum()).item())
    assert report.to_header()["quant_report"]["ah"]["mean_rel_mse"] == pytest.approx(sum(errors) / len(errors), rel=1e-6)
    without_rows = QuantConfig.from_preset("W4A4", scope="ah")
    assert quantize_(copy.deepcopy(demo), without_rows,
                     without_rows.select(demo, spec.components)).to_header()["quant_report"]["ah"]["mean_rel_mse"] is None


def test_gptq_refuses_float_formats_and_missing_hessians(calibrated):
    spec, demo, stats = calibrated["pi05"]
    policy = copy.deepcopy(demo)
    before = {k: v.clone() for k, v in policy.state_dict().items()}
    with pytest.raises(UserError, match=r"method 'gptq' implements W<b>\[G<g>\]\[A<a>\]; preset 'MXFP4'"):
        config = QuantConfig.from_preset("MXFP4", scope="ah", method="gptq", stats=stats)
        quantize_(policy, config, config.select(policy, spec.components))
    rows_only = calib.CalibrationStats("k", {}, {n: calib.ChannelStats(s.absmax, s.quantile, samples=s.samples)
                                                 for n, s in stats.layers.items()})
    with pytest.raises(UserError, match=r"GPTQ calibration statistics .* for 167 selected layers"):
        config = QuantConfig.from_preset("W4", scope="ah", method="gptq_act", stats=rows_only)
        quantize_(policy, config, config.select(policy, spec.components))
    assert all(torch.equal(before[k], v) for k, v in policy.state_dict().items())


def test_gptq_refuses_a_non_finite_hessian_before_rounding_and_an_indefinite_one_naming_the_layer(calibrated):
    spec, demo, stats = calibrated["pi05"]
    policy = copy.deepcopy(demo)
    before = {k: v.clone() for k, v in policy.state_dict().items()}
    ah = select_layers(policy, spec.components, "ah").flat()
    last = list(ah)[-1]
    bad = dict(stats.layers)
    bad[last] = copy.copy(stats.layers[last])
    # what one NaN input row leaves in the observer's statistics: a NaN absmax and a NaN row and column of X^T X
    bad[last].absmax = stats.layers[last].absmax.clone()
    bad[last].absmax[0] = float("nan")
    bad[last].hessian = stats.layers[last].hessian.clone()
    bad[last].hessian[0, :] = bad[last].hessian[:, 0] = float("nan")
    nan_stats = calib.CalibrationStats("nanstats", {}, bad)
    with pytest.raises(UserError, match=rf"layer {last}'s inputs held non-finite values while calibrating \(calibration "
                                        r"statistics nanstats.pt\)"):
        config = QuantConfig.from_preset("W4A8", scope="ah", method="gptq", stats=nan_stats)
        quantize_(policy, config, config.select(policy, spec.components))
    assert all(torch.equal(before[k], v) for k, v in policy.state_dict().items())  # the last layer's NaN refused first
    bad[last].absmax, bad[last].hessian = stats.layers[last].absmax, -torch.eye(bad[last].hessian.shape[0])
    with pytest.raises(UserError, match=rf"layer {last}'s Hessian plus damping \(0.01 of its mean diagonal\) is not positive"):
        config = QuantConfig.from_preset("W4A8", scope="ah", method="gptq", stats=calib.CalibrationStats("neg", {}, bad))
        quantize_(policy, config, config.select(policy, spec.components))
