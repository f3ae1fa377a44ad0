"""`fuse_activation_hooks` swaps the transform of quantize_'s counting hooks without changing what
they compute or count (CPU: the reference arithmetic runs; the fused kernel's bit-equality on CUDA
is checked by benchmarks/gpu_policy_inference.py, `checks.fused_equal_fraction`)."""

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
