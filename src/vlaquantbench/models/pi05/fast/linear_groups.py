"""Linear layers that read one input (q/k/v, gate/up), run as one matrix product.

At batch 1 the action expert's products are tiny (50 tokens), so a chunk's time goes to the number
of kernels rather than to arithmetic. A `LinearGroup` computes its members as one product with the
members' weights concatenated along the output dimension -- per output row the same dot products,
so per-channel and per-group weight quantization (applied in place before) is unchanged. Its input
comes from `input_from(op, args, compiler)`: the elementwise op that produces it (a norm, a GELU,
a head merge) run through each member's own `ActivationQuantizer.fused`, which quantizes the op's
output as the member's hook would, inside the same compiled function, and counts the member's run
(quantizers of one input compute it once, `quant.hooks`). Nothing here touches a count.

Real low-bit kernels group too: members of one packed class that names the per-token quantization
of its input (`input_cast`, e.g. `quant.kernels.fp8.Fp8DynamicLinear`) and can merge into one layer
(`merged`, whose weight the members' packed weights then view: no second copy), each with one
`CountingHook` that changes nothing. Their producer then computes the cast itself -- the low-bit
values and per-token scales, `CastRows`, in the op's own kernel -- and the merged layer's product
(`forward_cast`, e.g. `torch._scaled_mm`) reads them, so no separate quantization kernel runs.

Otherwise a group fuses only what it can prove equivalent: members that are plain `nn.Linear` layers with
floating weights (not packed real-kernel modules), no forward hooks, and either no pre-hooks or
exactly one `CountingHook` each whose transform only quantizes (no smoothing or clipping vectors,
which are per layer), all alike: per-token integer with one bit width, or one float format. Anything else -- a calibrated
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

from vlaquantbench.quant.grid import CastRows, PerTokenCast
from vlaquantbench.quant.hooks import ActivationQuantizer, CountingHook, quantizing_op


def _castable(layers: Sequence[nn.Module]) -> tuple[PerTokenCast | None, list[ActivationQuantizer]]:
    """(the cast their producer computes for them, the members' counting quantizers) for packed
    real-kernel layers that can run as one merged product on an input cast by its producer;
    (None, []) for any other."""
    first = layers[0]
    cast = getattr(first, "input_cast", None)
    if cast is None or not hasattr(type(first), "merged"):
        return None, []
    quantizers = []
    for layer in layers:
        pre = list(layer._forward_pre_hooks.values())
        if (type(layer) is not type(first) or layer.input_cast != cast or layer._forward_hooks
                or len(pre) != 1 or not isinstance(pre[0], CountingHook) or not pre[0].quantizer.is_plain
                or pre[0].quantizer.plain_quantization is not None or layer.in_features != first.in_features
                or layer.out_dtype != first.out_dtype or (layer.bias is None) != (first.bias is None)):
            return None, []
        quantizers.append(pre[0].quantizer)
    return cast, quantizers


def _fusable(layers: Sequence[nn.Module]) -> tuple[bool, list[ActivationQuantizer]]:
    """(can fuse, the members' quantizers -- one per member, or none)."""
    quantizers: list[ActivationQuantizer] = []
    first = layers[0]
    for layer in layers:
        if type(layer) is not nn.Linear or layer._forward_hooks or layer._backward_hooks:
            return False, []
        weight = layer.weight
        if not weight.is_floating_point() or weight.dtype != first.weight.dtype or weight.device != first.weight.device:
            return False, []
        if (layer.bias is None) != (first.bias is None) or layer.in_features != first.in_features:
            return False, []
        pre = list(layer._forward_pre_hooks.values())
        if len(pre) > 1 or (pre and not isinstance(pre[0], CountingHook)):
            return False, []
        if pre:
            quantizers.append(pre[0].quantizer)
    if quantizers and (len(quantizers) != len(layers) or not all(q.is_plain for q in quantizers)
                       or len({q.plain_quantization for q in quantizers}) != 1):
        return False, []
    return True, quantizers


class LinearGroup:
    """`group(group.input_from(op, args, compiler))` returns the members' outputs, in member order."""

    def __init__(self, layers: Sequence[nn.Module]):
        self.layers = list(layers)
        self._input: torch.Tensor | CastRows | None = None
        self.deferred_bias: torch.Tensor | None = None
        self.sizes = [layer.out_features for layer in self.layers]
        self.cast, self.quantizers = _castable(self.layers)
        if self.cast is not None:
            self.fused, self.merged = True, type(self.layers[0]).merged(self.layers)
            return
        self.fused, self.quantizers = _fusable(self.layers)
        if not self.fused:
            return
        with torch.no_grad():
            if len(self.layers) == 1:
                self.weight, self.bias = self.layers[0].weight, self.layers[0].bias
            else:
                self.weight = torch.cat([layer.weight for layer in self.layers])
                biases = [layer.bias for layer in self.layers]
                self.bias = None if biases[0] is None else torch.cat(biases)

    @property
    def input_quantization(self):
        """The quantization the members apply to their input inside the producer: per-token bits, a
        float format or a real kernel's cast (None: none)."""
        if self.cast is not None:
            return self.cast
        return self.quantizers[0].plain_quantization if self.quantizers else None

    def input_from(self, op: Callable, args: tuple, compiler: Callable | None = None):
        """`op(*args)`, whose output (the last, if several) is this group's input: quantized by
        every member's quantizer when the group is fused, as is otherwise (an unfused group's
        members quantize through their hooks when called). `compiler` as in
        `ActivationQuantizer.fused`."""
        if self.quantizers:
            out = [quantizer.fused(op, *args, compiler=compiler, cast=self.cast) for quantizer in self.quantizers][0]
        else:
            out = quantizing_op(op, None, compiler)(*args)
        self._input = out[-1] if isinstance(out, tuple) and not isinstance(out, CastRows) else out
        return out

    def __call__(self, x: torch.Tensor | CastRows, defer_bias: bool = False) -> list[torch.Tensor]:
        """The members' outputs. `defer_bias`: a one-member cast group whose float32 output
        `torch._scaled_mm` cannot add a bias to leaves it out, for the op that reads the output to
        add (the same float32 addition, without a pass of its own over the output); `deferred_bias`
        is then that bias, else None."""
        if x is not self._input:
            raise ValueError("a linear group's input must come from its input_from(), which quantizes it")
        self.deferred_bias = None
        if not self.fused:
            return [layer(x) for layer in self.layers]
        if self.cast is not None:
            if (defer_bias and len(self.layers) == 1 and self.merged.bias is not None
                    and self.merged.out_dtype == torch.float32):
                self.deferred_bias = self.merged.bias
            y = self.merged.forward_cast(x, with_bias=self.deferred_bias is None)
        else:
            y = F.linear(x, self.weight, self.bias)
        return [y] if len(self.layers) == 1 else list(y.split(self.sizes, dim=-1))
