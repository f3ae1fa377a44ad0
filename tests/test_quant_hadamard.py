"""The Hadamard transform (vlaquantbench.quant.transforms.Hadamard) on the demo pi0.5 and pi0 (real lerobot
architectures, random weights, float32): function preserving without quantization, on the declared grids
with every hook fired when composed with RTN, and composed with GPTQ through rotated Hessians."""

import copy

import pytest
import torch
from pi_chunks import pi_chunk

from vlaquantbench.models import get_model_spec
from vlaquantbench.quant import QuantConfig, quantize_, select_layers
from vlaquantbench.quant import calibration as calib
from vlaquantbench.quant.transforms import BlockHadamard

MODELS = ("pi05", "pi0")


@pytest.fixture(scope="module")
def demos():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield {name: (get_model_spec(name), get_model_spec(name).build("demo", device="cpu", seed=0)) for name in MODELS}
    torch.set_num_threads(threads)


def test_block_hadamard_is_orthonormal_for_any_width():
    for width, block in ((256, 256), (96, 32), (1152, 128), (4304, 16)):
        rotation = BlockHadamard(width)
        assert rotation.block == block
        x = torch.randn(3, width, dtype=torch.float64)
        rotated = rotation.rotate(x, torch.float64)
        assert torch.allclose(rotated.norm(dim=1), x.norm(dim=1)) and not torch.allclose(rotated, x)
        assert torch.allclose(rotation.rotate(rotated, torch.float64), x)  # Sylvester H_b is symmetric: R R = I


@pytest.mark.parametrize("model_name", MODELS)
def test_rotated_unquantized_model_produces_the_same_actions(demos, model_name):
    spec, demo = demos[model_name]
    rotated = copy.deepcopy(demo)
    with torch.no_grad():
        reference = pi_chunk(model_name, demo, 3)
        config = QuantConfig.from_preset("BASELINE", scope="e2e", method="hadamard")
        report = quantize_(rotated, config, config.select(rotated, spec.components))
        actions = pi_chunk(model_name, rotated, 3)
    rel_l2 = ((actions - reference).norm() / reference.norm()).item()
    changed = sum(not torch.equal(layer.weight, demo.get_submodule(name).weight)
                  for name, layer in report.selection.flat().items())
    print(f"{model_name}: {changed} of {len(report.selection.flat())} e2e weights rotated, action rel L2 {rel_l2:.2e}")
    assert changed == len(report.selection.flat()) and report.unfired() == []
    assert rel_l2 <= 1e-4


def test_hadamard_w4a4_keeps_weights_and_inputs_on_the_grid(demos):
    spec, demo = demos["pi05"]
    policy = copy.deepcopy(demo)
    config = QuantConfig.from_preset("W4A4", scope="e2e", method="hadamard")
    report = quantize_(policy, config, config.select(policy, spec.components))
    with torch.no_grad():
        pi_chunk("pi05", policy, 3)
    header = report.to_header()
    assert header["hooks"] == {"selected": 456, "fired": 456, "unfired": []}
    assert header["quant_format"].endswith("block-Hadamard transforms folded into the weights (QuaRot online form)")
    for name, layer in report.selection.flat().items():
        groups = layer.weight.reshape(layer.out_features, -1, min(128, layer.in_features))
        assert max(len(torch.unique(row)) for row in groups.reshape(-1, groups.shape[-1])) <= 16, name
    hook = report.result.hooks["action_out_proj"]
    x = torch.randn(5, policy.get_submodule("action_out_proj").in_features)
    quantized = hook.transform(x)
    assert all(len(torch.unique(row)) <= 16 for row in quantized)  # 4-bit per token, after the rotation
    assert not torch.allclose(quantized, hook.transform.steps[-1](x))  # the rotation ran before quantizing


def test_hadamard_gptq_rounds_in_the_rotated_space(demos):
    spec, demo = demos["pi0"]
    layers = select_layers(demo, spec.components, "ah").flat()
    with torch.no_grad(), calib.observe(layers, quantile=None, sample_rows=128, hessian=True) as observer:
        pi_chunk("pi0", demo, 0)
    stats = observer.stats("hadgptq", {})
    name = "paligemma_with_expert.gemma_expert.model.layers.0.mlp.down_proj"
    rotation = BlockHadamard(layers[name].in_features)
    observed = stats.layers[name]
    assert observed.sample_stride == 1 and observed.rows == observed.samples.shape[0]  # every row kept
    rows = rotation.rotate(observed.samples.double(), torch.float64)
    expected = rows.t() @ rows  # the second moment of the rotated inputs
    mapped = rotation.map_hessian(observed.hessian.double())
    assert torch.allclose(mapped, expected, rtol=1e-5, atol=1e-5 * expected.abs().max().item())
    policy = copy.deepcopy(demo)
    with torch.no_grad():
        config = QuantConfig.from_preset("W4A8", scope="ah", method="hadamard_gptq", stats=stats)
        report = quantize_(policy, config, config.select(policy, spec.components))
        pi_chunk("pi0", policy, 3)
    header = report.to_header()
    assert header["hooks"] == {"selected": 131, "fired": 131, "unfired": []}
    assert header["quant_report"]["gptq"]["error_vs_rtn_max"] <= 1.0  # against RTN of the rotated weights
    assert 0 < header["quant_report"]["ah"]["mean_rel_mse"] < 1
