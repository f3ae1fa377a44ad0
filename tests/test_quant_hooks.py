"""Only the activation quantizer counts: through its hook, or through the fused form a fast path
uses to quantize inside the op that produces a layer's input (`ActivationQuantizer.fused`)."""

import pytest
import torch
from torch import nn

from vlaquantbench.quant.grid import fake_quant_activation
from vlaquantbench.quant.hooks import CountingHook
from vlaquantbench.quant.input_transform import InputTransform


def _norm(x: torch.Tensor, eps: float):
    return x, x * torch.rsqrt(x.pow(2).mean(-1, keepdim=True) + eps)


def test_the_hook_counts_through_its_quantizer():
    layer = nn.Linear(8, 4)
    hook = CountingHook(layer, InputTransform(act_bits=4))
    x = torch.randn(3, 8)
    assert torch.equal(layer(x), nn.functional.linear(fake_quant_activation(x, 4), layer.weight, layer.bias))
    assert hook.calls == hook.quantizer.calls == 1
    with pytest.raises(AttributeError):
        hook.calls = 0  # the count is the quantizer's, read-only from outside


def test_fused_quantizes_the_last_output_and_each_member_counts_its_run():
    layers = [nn.Linear(8, 4) for _ in range(3)]
    quantizers = [CountingHook(layer, InputTransform(act_bits=4)).quantizer for layer in layers]
    x = torch.randn(2, 5, 8)
    results = [q.fused(_norm, x, 1e-6) for q in quantizers]
    hidden, normed = results[0]
    assert hidden is x and torch.equal(normed, fake_quant_activation(_norm(x, 1e-6)[1], 4))
    assert all(r[1] is normed for r in results)  # one input, quantized once
    assert [q.calls for q in quantizers] == [1, 1, 1]
    x.mul_(2)  # an input changed in place is quantized again
    again = quantizers[0].fused(_norm, x, 1e-6)[1]
    assert again is not normed and torch.equal(again, fake_quant_activation(_norm(x, 1e-6)[1], 4))
    assert quantizers[0].calls == 2


def test_only_plain_per_token_quantization_can_be_fused():
    smoothed = CountingHook(nn.Linear(8, 4), InputTransform(smooth=torch.rand(8) + 0.5, act_bits=4)).quantizer
    assert not smoothed.is_plain
    with pytest.raises(ValueError, match="not plain per-token or float-format quantization"):
        smoothed.fused(_norm, torch.randn(2, 8), 1e-6)
    assert smoothed.calls == 0  # nothing ran


def test_float_format_quantizers_fuse_as_their_hooks_quantize():
    from vlaquantbench.quant.presets import FORMATS

    fmt = FORMATS["NVFP4"]
    layers = [nn.Linear(40, 4).to(torch.bfloat16) for _ in range(2)]
    quantizers = [CountingHook(layer, InputTransform(act_format=fmt)).quantizer for layer in layers]
    assert quantizers[0].plain_quantization is fmt
    x = torch.randn(2, 5, 40, dtype=torch.bfloat16)
    normed = quantizers[0].fused(_norm, x, 1e-6)[1]
    assert quantizers[1].fused(_norm, x, 1e-6)[1] is normed and [q.calls for q in quantizers] == [1, 1]
    produced = _norm(x, 1e-6)[1]
    assert torch.equal(normed, InputTransform(act_format=fmt)(produced)) and not torch.equal(normed, produced)
