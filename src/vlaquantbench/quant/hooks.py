"""Activation quantizers that count their own runs, and the pre-hooks that install them on linears.

The count is the evidence that a layer's input was really transformed during a run (paper
`sec:pitfalls`, "Activation coverage"): a hook installed on a module that the forward path never
calls leaves the run silently weight-only for that layer. Only `ActivationQuantizer` advances a
count, and only when it computes (or, for an input it has just seen quantized the same way,
returns) its layer's transformed input: through its hook, or through `fused`, the form a fast
path uses to quantize inside the op that produces the input.
"""

from __future__ import annotations

import functools
import types
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import nn

from vlaquantbench.quant.grid import CastRows, PerTokenCast, fake_quant_activation
from vlaquantbench.quant.input_transform import InputTransform
from vlaquantbench.quant.presets import FloatFormat


@dataclass(frozen=True)
class Rotated:
    """The quantization of a rotated input (`plain_quantization` of a transform with a rotation):
    `rotation(x)`, then `quantization` (per-token bits, a float format, or None: none)."""

    rotation: Callable[[torch.Tensor], torch.Tensor]
    quantization: int | FloatFormat | None

    @property
    def name(self) -> str:
        inner = self.quantization
        return f"{self.rotation.name}_" + (f"int{inner}" if isinstance(inner, int) else getattr(inner, "name", "none"))


class ActivationQuantizer:
    """One layer's input transform and the number of times it ran."""

    def __init__(self, transform: Callable[[torch.Tensor], torch.Tensor]):
        self.transform = transform
        self.calls = 0

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        self.calls += 1
        return self.transform(x)

    def reset_calls(self) -> None:
        self.calls = 0

    @property
    def plain_quantization(self) -> int | FloatFormat | Rotated | None:
        """What a transform that only quantizes, possibly after a rotation shared by every layer of
        its width, does: the bit width of per-token integer quantization, or the float format, or
        `Rotated` (None: a transform that changes nothing). `fused` needs such a transform;
        ValueError for any other (smoothing or clipping vectors, which are per layer, a wrapped
        transform). The Triton form (`quant.fused_kernel`) exposes the transform it computes as
        `reference`."""
        transform = getattr(self.transform, "reference", self.transform)
        if not isinstance(transform, InputTransform) or transform.smooth is not None or transform.clip is not None:
            raise ValueError(f"{type(self.transform).__name__} is not plain per-token or float-format quantization")
        quantization = transform.act_format if transform.act_format is not None else transform.act_bits
        return quantization if transform.rotation is None else Rotated(transform.rotation, quantization)

    @property
    def is_plain(self) -> bool:
        try:
            self.plain_quantization
        except ValueError:
            return False
        return True

    def fused(self, op: Callable, *args, compiler: Callable | None = None, cast: PerTokenCast | None = None):
        """`op(*args)` with its output (the last one, if it returns several) quantized as this
        quantizer quantizes its layer's input -- in the same compiled function when `compiler`
        (e.g. `torch.compile` with options) is given, so the compiler fuses the quantization into
        the producing op. Counts one run. Quantizers of layers that read the same input (q/k/v)
        each call this with the same `op` and arguments; the second and later calls return the
        first one's result instead of computing it again (`_LastFused`).

        `cast`: the layer is a real low-bit kernel whose own input quantization is `cast` (its
        quantizer only counts, changing nothing); the output comes back as that kernel's input,
        `CastRows` of low-bit values and per-token scales, computed inside the producing op."""
        quantization = self.plain_quantization
        if cast is not None:
            if quantization is not None:
                raise ValueError(f"a layer whose kernel casts its input to {cast.name} cannot also fake-quantize it "
                                 f"({quantization})")
            quantization = cast
        self.calls += 1
        return _LAST_FUSED.lookup_or_run(quantizing_op(op, quantization, compiler), args)


class _LastFused:
    """The last `fused` result with its inputs (held, so identities stay valid): an equal
    quantizer (same op, bit width and compiler, hence the same function) on the same argument
    objects, none modified since (tensor `_version`), gets the same result."""

    def __init__(self):
        self.key: tuple | None = None
        self.result = None

    def lookup_or_run(self, fn: Callable, args: tuple):
        key = (fn, args, tuple(a._version if isinstance(a, torch.Tensor) else None for a in args))
        if self.key is not None and _same(self.key, key):
            return self.result
        self.key, self.result = key, fn(*args)
        return self.result


def _same(a: tuple, b: tuple) -> bool:
    (fn_a, args_a, versions_a), (fn_b, args_b, versions_b) = a, b
    return (fn_a is fn_b and len(args_a) == len(args_b) and versions_a == versions_b
            and all(x is y if isinstance(x, torch.Tensor) else x == y for x, y in zip(args_a, args_b)))


_LAST_FUSED = _LastFused()


@functools.cache
def quantizing_op(op: Callable, quantization: int | FloatFormat | PerTokenCast | Rotated | None,
                  compiler: Callable | None = None) -> Callable:
    """`op` followed by the quantization of its (last) output -- per-token with `quantization` bits,
    in a float format, rotated first (`Rotated`: the rotation's products then run inside the same
    compiled function), or cast to a real kernel's low-bit input (`PerTokenCast`: that output comes
    back as `CastRows`) -- as one function (None: `op` alone), compiled once by `compiler` when given.

    An op may name a hand-written kernel for itself followed by per-token quantization,
    `op.per_token_kernel(*args, bits=)`, bit-identical to the composition, or one for the
    quantization of its (last) output alone, `op.per_token_quantizer(x, bits)`, run after the op
    compiled by itself (for ops whose compiled composition is slower than the two), with
    `op.per_token_kernel_supports(first_arg)`; where the compiled form is asked for and the kernel
    supports the input, it runs instead of the compiled composition. A rotated per-token integer
    quantization runs on CUDA as the op compiled alone, then one Triton kernel for the rotation and
    the quantization, or as `op.rotated_kernel(*args, rotation=, bits=)` where the op names one
    (`_rotating_kernel_or`)."""
    if quantization is None:
        return compiler(op) if compiler is not None else op
    # A compiler may name the form of x / scale its code computes exactly (`Inductor.quotient`).
    quotient = getattr(compiler, "quotient", torch.div)

    def fn(*args):
        return _on_last_output(op(*args), lambda x: _quantized(x, quantization, quotient))

    if compiler is None:
        return _as_cast_rows(fn) if isinstance(quantization, PerTokenCast) else fn
    # A code object of its own per op and bit width: dynamo keeps its compilations (and their
    # recompile limit) per code object, and every `fn` closure would otherwise share one.
    name = f"{op.__name__}_then_" + (f"int{quantization}" if isinstance(quantization, int) else quantization.name)
    compiled = compiler(types.FunctionType(fn.__code__.replace(co_name=name, co_qualname=name), fn.__globals__, name,
                                           None, fn.__closure__))
    if isinstance(quantization, PerTokenCast):
        return _as_cast_rows(compiled)
    if isinstance(quantization, Rotated) and isinstance(quantization.quantization, int):
        return _rotating_kernel_or(compiled, op, quantization, compiler)
    supports = getattr(op, "per_token_kernel_supports", None)
    if supports is None or not isinstance(quantization, int):  # the kernels quantize unrotated integer rows
        return compiled
    kernel = getattr(op, "per_token_kernel", None)
    if kernel is None:
        plain, quantizer = compiler(op), op.per_token_quantizer

        def kernel(*args, bits):
            return _on_last_output(plain(*args), lambda x: quantizer(x, bits))

    def kernel_or_compiled(*args):
        return kernel(*args, bits=quantization) if supports(args[0]) else compiled(*args)

    return kernel_or_compiled


def _rotating_kernel_or(compiled: Callable, op: Callable, quantization: Rotated, compiler: Callable) -> Callable:
    """For a rotated per-token integer quantization: on CUDA, `op` compiled alone, then the rotation
    and the quantization of its (last) output in one Triton kernel (`quant.fused_kernel.
    rotated_fake_quant`: one read of the row, the products on the tensor cores). Compiled together,
    inductor ran the rotation as float32 products of their own, with float32 copies around them:
    1.5-1.6x BASELINE's chunk for W4A4 on an H200, against 1.02-1.05x unrotated. Elsewhere (or for a
    rotation the kernel does not compute) `compiled`."""
    from vlaquantbench.quant import fused_kernel  # Triton, imported only where a rotated kernel is asked for

    if not fused_kernel.supports_rotation(quantization.rotation):
        return compiled
    rotation, bits = quantization.rotation, quantization.quantization
    kernel = getattr(op, "rotated_kernel", None)  # the op, its rotation and quantization in one kernel
    plain = compiler(op) if kernel is None else None

    def rotated_kernel_or_compiled(*args):
        if not fused_kernel.supports(args[0]):
            return compiled(*args)
        if kernel is not None:
            return kernel(*args, rotation=rotation, bits=bits)
        return _on_last_output(plain(*args), lambda x: fused_kernel.rotated_fake_quant(x, rotation, bits))

    return rotated_kernel_or_compiled


def _on_last_output(out, transform: Callable):
    """`transform` of an op's output, or of the last one where it returns several (a residual add
    returns the new hidden state and its normalized copy, which a layer reads)."""
    return (*out[:-1], transform(out[-1])) if isinstance(out, tuple) else transform(out)


def _as_cast_rows(fn: Callable) -> Callable:
    """`fn`, whose (last) output is a `PerTokenCast`'s (values, scales), returning it as `CastRows`.
    The tuple is wrapped outside `fn`: what a compiled function returns stays plain tensors."""

    def with_cast_rows(*args):
        out = fn(*args)
        if isinstance(out[-1], tuple):  # the op returned several outputs, the last one cast
            return (*out[:-1], CastRows(*out[-1]))
        return CastRows(*out)

    return with_cast_rows


def _quantized(x: torch.Tensor, quantization: int | FloatFormat | PerTokenCast | Rotated,
               quotient: Callable = torch.div):
    """What the hook's `InputTransform` does to `x` (or, for a `PerTokenCast`, what a real kernel
    does to its input: (values, scales)), written so that a compiler fusing it into the op that
    made `x` still quantizes the rounded `x` a hook would see."""
    if isinstance(quantization, Rotated):  # the rotation's own float32 arithmetic, rounded to x's dtype
        x = quantization.rotation(x)
        return x if quantization.quantization is None else _quantized(x, quantization.quantization, quotient)
    if isinstance(quantization, PerTokenCast):
        return tuple(quantization(_as_float32(x), quotient))
    if isinstance(quantization, FloatFormat):
        return quantization.quantize_activation(_as_float32(x)).to(x.dtype)
    return fake_quant_activation(_as_float32(x), quantization, quotient).to(x.dtype)


def _as_float32(x: torch.Tensor) -> torch.Tensor:
    """`x.float()` for a bf16 tensor, written as the bit-level widening it is. Inside one fused
    kernel a compiler may drop a float32 -> bf16 -> float32 round trip and quantize the unrounded
    value; a hook sees the rounded bf16 tensor, and this form keeps that rounding."""
    if x.dtype != torch.bfloat16:
        return x.float()
    return (x.view(torch.int16).to(torch.int32) << 16).view(torch.float32)


class CountingHook:
    """A forward pre-hook that passes a linear layer's input through its `ActivationQuantizer`."""

    def __init__(self, layer: nn.Linear, transform: Callable[[torch.Tensor], torch.Tensor]):
        self.quantizer = ActivationQuantizer(transform)
        self.handle = layer.register_forward_pre_hook(self)

    def __call__(self, module: nn.Module, args: tuple) -> tuple:
        return (self.quantizer(args[0]), *args[1:])

    @property
    def transform(self) -> Callable[[torch.Tensor], torch.Tensor]:
        return self.quantizer.transform

    @transform.setter
    def transform(self, transform: Callable[[torch.Tensor], torch.Tensor]) -> None:
        """Swap how the input is computed (e.g. the fused kernel); the count stays."""
        self.quantizer.transform = transform

    @property
    def calls(self) -> int:
        return self.quantizer.calls

    def remove(self) -> None:
        self.handle.remove()
