"""Layer diagnostics: the per-call measures and the observer that averages them over calls."""

import math

import pytest
import torch
from torch import nn

from vlaquantbench.diagnostics.collect import DiagnosticsObserver
from vlaquantbench.diagnostics.measures import dispersion, kurtosis, layer_measures, relative_error
from vlaquantbench.quant.grid import fake_quant_activation, fake_quant_weight


def test_kurtosis_is_the_pearson_fourth_moment():
    assert kurtosis(torch.tensor([1.0, -1.0] * 8)) == pytest.approx(1.0)
    gauss = torch.randn(200_000, generator=torch.Generator().manual_seed(0))
    assert kurtosis(gauss) == pytest.approx(3.0, abs=0.05)
    spiky = torch.zeros(1000)
    spiky[0] = 10.0
    assert kurtosis(spiky) > 100
    assert math.isnan(kurtosis(torch.ones(5)))


def test_relative_error_and_dispersion():
    x = torch.tensor([[3.0, 4.0]])
    assert relative_error(x, x) == 0.0
    assert relative_error(x * 1.1, x) == pytest.approx(0.1)
    assert dispersion(torch.tensor([[1.0, -2.0]])) == 1.0  # one token
    assert dispersion(torch.tensor([[1.0, 0.0], [0.0, -1.0], [4.0, 0.0]])) == pytest.approx(4.0 / 2.0)


def test_layer_measures_vanish_without_quantization():
    layer = nn.Linear(8, 4)
    x = torch.randn(5, 8)
    m = layer_measures(x, layer.weight, layer.bias, x, layer.weight)
    assert m["out_rel_err"] == 0.0 and m["act_rel_err"] == 0.0


def test_observer_averages_w4a4_errors_over_calls_on_real_layers():
    torch.manual_seed(0)
    model = nn.Sequential(nn.Linear(256, 64), nn.ReLU(), nn.Linear(64, 16))
    layers = {"0": model[0], "2": model[2]}
    inputs = [torch.randn(3, 256), torch.randn(5, 256) * 3]
    with DiagnosticsObserver(layers, "W4A4") as observer, torch.no_grad():
        for x in inputs:
            model(x)
    result = observer.result()
    assert result["0"]["calls"] == result["2"]["calls"] == 2
    assert result["0"]["params"] == 256 * 64 and result["2"]["in_features"] == 64
    w = model[0].weight.detach()
    qw = fake_quant_weight(w, 4, 128, False)  # W4: asymmetric, groups of 128
    expected = sum(
        layer_measures(x, w, model[0].bias, fake_quant_activation(x, 4), qw)["out_rel_err"] for x in inputs
    ) / 2
    assert result["0"]["out_rel_err"] == pytest.approx(expected)
    assert 0 < result["0"]["act_rel_err"] < 1
    # Hooks are gone after the context: further calls are not counted.
    model(torch.randn(1, 256))
    assert observer.calls["0"] == 2


def test_weight_only_preset_leaves_activations_exact():
    layer = nn.Linear(128, 8)
    with DiagnosticsObserver({"l": layer}, "W4") as observer, torch.no_grad():
        layer(torch.randn(4, 128))
    out = observer.result()["l"]
    assert out["act_rel_err"] == 0.0 and out["out_rel_err"] > 0
