"""Linear layers that read one input (q/k/v, gate/up), run as one matrix product.

At batch 1 the action expert's products are tiny (50 tokens), so a chunk's time goes to the number
of kernels rather than to arithmetic. A `LinearGroup` computes its members as one product with the
members' weights concatenated along the output dimension -- per output row the same dot products,
so per-channel and per-group weight quantization (applied in place before) is unchanged -- and
applies their activation quantization once, as the members' hooks would (they read the same
input). Each member's hook still counts the call, so hook coverage is proven as before.

A group fuses only what it can prove equivalent: members that are plain `nn.Linear` layers with
floating weights (not packed real-kernel modules), no forward hooks, and either no pre-hooks or
exactly one `CountingHook` each whose transform is plain per-token quantization (no smoothing or
clipping vectors, which are per layer) with the same bit width. Anything else -- a calibrated
transform, a wrapped transform, a packed layer -- runs member by member through the modules, hooks
included.

The weights are copied when the group is made: make groups after quantization (the captured
sampler makes them when it captures, and drops them on `reset()`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
import torch.nn.functional as F  # noqa: N812
from torch import nn

from vlaquantbench.quant.grid import fake_quant_activation
from vlaquantbench.quant.hooks import CountingHook, InputTransform

_UNSET = object()


def _plain_act_bits(transform) -> int | None | object:
    """The bit width of a transform that only quantizes per token (None: identity); `_UNSET` for
    anything else. `FusedInputTransform` (quant.fused_kernel) exposes its reference's fields."""
    reference = getattr(transform, "reference", transform)
    if (not isinstance(reference, InputTransform) or reference.smooth is not None or reference.clip is not None
            or reference.act_format is not None):  # float formats quantize through the members' hooks
        return _UNSET
    return reference.act_bits


def _fusable(layers: Sequence[nn.Module]) -> tuple[bool, int | None, list[CountingHook]]:
    """(can fuse, common activation bits, the members' counting hooks)."""
    hooks: list[CountingHook] = []
    bits: set = set()
    first = layers[0]
    for layer in layers:
        if type(layer) is not nn.Linear or layer._forward_hooks or layer._backward_hooks:
            return False, None, []
        weight = layer.weight
        if not weight.is_floating_point() or weight.dtype != first.weight.dtype or weight.device != first.weight.device:
            return False, None, []
        if (layer.bias is None) != (first.bias is None) or layer.in_features != first.in_features:
            return False, None, []
        pre = list(layer._forward_pre_hooks.values())
        if len(pre) > 1 or (pre and not isinstance(pre[0], CountingHook)):
            return False, None, []
        if pre:
            hooks.append(pre[0])
            bits.add(_plain_act_bits(pre[0].transform))
        else:
            bits.add(None)
    if len(bits) != 1 or _UNSET in bits or (hooks and len(hooks) != len(layers)):
        return False, None, []
    return True, bits.pop(), hooks


class LinearGroup:
    """`group(x)` returns the members' outputs for input `x`, in member order.

    `act_bits` is the per-token quantization the members apply to their input (None: none). A
    producer that has already quantized `x` that way (a fused norm) passes `prequantized=True`.
    """

    def __init__(self, layers: Sequence[nn.Module], quantize: Callable[[torch.Tensor, int], torch.Tensor] | None = None):
        self.layers = list(layers)
        self.fused, self.act_bits, self.hooks = _fusable(self.layers)
        self.quantize = quantize or fake_quant_activation
        if not self.fused:
            self.act_bits = None
            return
        self.sizes = [layer.out_features for layer in self.layers]
        with torch.no_grad():
            if len(self.layers) == 1:
                self.weight, self.bias = self.layers[0].weight, self.layers[0].bias
            else:
                self.weight = torch.cat([layer.weight for layer in self.layers])
                biases = [layer.bias for layer in self.layers]
                self.bias = None if biases[0] is None else torch.cat(biases)

    def __call__(self, x: torch.Tensor, prequantized: bool = False) -> list[torch.Tensor]:
        if not self.fused:
            if prequantized:
                raise ValueError("an unfused group quantizes through its hooks; do not pass a prequantized input")
            return [layer(x) for layer in self.layers]
        for hook in self.hooks:
            hook.calls += 1
        if self.act_bits is not None and not prequantized:
            x = self.quantize(x, self.act_bits)
        y = F.linear(x, self.weight, self.bias)
        return [y] if len(self.layers) == 1 else list(y.split(self.sizes, dim=-1))
