"""What every real-kernel method shares: `PackedLinear` (a linear whose weight lives in a packed
format), `PerTokenLinear` (W8A8 with per-token input rows, `quantize_per_token`), and `replace_all`,
which swaps each selected linear for its packed module and reports the memory it released."""

from __future__ import annotations

import torch
from torch import nn

from vlaquantbench.quant.apply import MethodResult, QuantConfig
from vlaquantbench.quant.grid import SCALE_FLOOR, CastRows, PerTokenCast
from vlaquantbench.quant.hooks import CountingHook
from vlaquantbench.quant.input_transform import InputTransform
from vlaquantbench.quant.methods import get_method
from vlaquantbench.quant.scope import Selection

try:  # one-pass activation quantization on CUDA; the torch expression below elsewhere
    import triton
    import triton.language as tl
    from triton.language.extra import libdevice
except ImportError:  # pragma: no cover
    triton = None

FP8 = torch.float8_e4m3fn
FP8_MAX = torch.finfo(FP8).max
# Made once: dynamo, tracing `quantize_per_token` inside a compiled model, cannot construct them.
_CASTS = {torch.int8: PerTokenCast(torch.int8), FP8: PerTokenCast(FP8)}

if triton is not None:

    @triton.jit
    def _quantize_rows(x_ptr, q_ptr, scale_ptr, n_cols, q_max, scale_floor, TO_INT: tl.constexpr, BLOCK: tl.constexpr):
        row = tl.program_id(0).to(tl.int64)
        cols = tl.arange(0, BLOCK)
        inside = cols < n_cols
        x = tl.load(x_ptr + row * n_cols + cols, mask=inside, other=0.0).to(tl.float32)
        scale = tl.maximum(tl.max(tl.abs(x), axis=0), scale_floor) / q_max
        y = tl.minimum(tl.maximum(x / scale, -q_max), q_max)
        if TO_INT:
            y = libdevice.rint(y)
        tl.store(q_ptr + row * n_cols + cols, y.to(q_ptr.dtype.element_ty), mask=inside)
        tl.store(scale_ptr + row, scale)


def quantize_per_token(x2d: torch.Tensor, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """Symmetric per-row quantization to int8 (round to nearest) or FP8 e4m3 (cast): (values, scales
    as a float32 column). One Triton kernel in eager CUDA code; the same arithmetic as torch ops
    elsewhere and under `torch.compile`, where inductor fuses those ops into the kernel that
    produces `x2d` (e.g. the RMSNorm before a projection) instead of launching a kernel of its own."""
    q_max = 127.0 if dtype == torch.int8 else FP8_MAX
    if triton is not None and x2d.is_cuda and not torch.compiler.is_compiling():
        x2d = x2d.contiguous()
        rows, cols = x2d.shape
        values = torch.empty(rows, cols, dtype=dtype, device=x2d.device)
        scales = torch.empty(rows, 1, dtype=torch.float32, device=x2d.device)
        block = triton.next_power_of_2(cols)
        _quantize_rows[(rows,)](x2d, values, scales, cols, q_max, SCALE_FLOOR, TO_INT=dtype == torch.int8,
                                BLOCK=block, num_warps=min(16, max(1, block // 512)))
        return values, scales
    return tuple(_CASTS[dtype](x2d))


class PackedLinear(nn.Module):
    """A linear layer whose weight lives in a packed format: keeps the bias, the sizes and the
    output dtype of the layer it replaces; subclasses compute `x2d @ W^T` in `_matmul`."""

    def __init__(self, linear: nn.Linear):
        super().__init__()
        self.in_features, self.out_features = linear.in_features, linear.out_features
        self.bias = linear.bias
        self.out_dtype = linear.weight.dtype

    @property
    def weight(self) -> torch.Tensor:
        """The replaced layer's weight as shape and dtype alone (a meta tensor: no data, and any
        arithmetic with it fails), for code that only reads them: lerobot's pi0.5 Gemma stack casts
        its hidden states to `q_proj.weight.dtype`, so its eager forward needs it."""
        return torch.empty(self.out_features, self.in_features, dtype=self.out_dtype, device="meta")

    def _matmul(self, x2d: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def _output(self, y2d: torch.Tensor, leading: torch.Size, with_bias: bool = True) -> torch.Tensor:
        y = y2d.to(self.out_dtype)
        if with_bias and self.bias is not None:
            y = y + self.bias
        return y.reshape(*leading, -1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self._output(self._matmul(x.reshape(-1, x.shape[-1])), x.shape[:-1])


class PerTokenLinear(PackedLinear):
    """W8A8 with per-output-channel weight scales (`weight_scale`, 1 x out, float32) and per-token
    input scales: subclasses hold the low-bit weight in the buffer named `WEIGHT`, quantize their
    input rows to `INPUT` and compute the scaled product in `_product(values, scales)`.

    Per token, the input's quantization is `input_cast`, which a fast path may compute inside the
    op that produces the input (`forward_cast` then takes the cast rows), and layers that read one
    input may run as one product (`merged`)."""

    WEIGHT: str
    INPUT: torch.dtype

    @property
    def per_token_input(self) -> bool:
        """Whether the input is quantized per token with nothing else applied to it first."""
        raise NotImplementedError

    @property
    def input_cast(self) -> PerTokenCast | None:
        """The per-token quantization of this layer's input, for a producer to compute (None:
        tensor-wise or static scales, or a per-layer input transform, which this layer computes itself)."""
        return _CASTS[self.INPUT] if self.per_token_input else None

    def _as_merged(self) -> None:
        """Set the attributes of a merged layer (plain per-token input) beyond the common ones."""
        raise NotImplementedError

    @classmethod
    def merged(cls, layers: list[PerTokenLinear]) -> PerTokenLinear:
        """One per-token layer computing `layers` (which read one input) as one product, their
        outputs concatenated in order: per output channel the same weights and scales. The
        members' low-bit weights become views of the merged weight, so the merge keeps no second copy."""
        first = layers[0]
        if len(layers) == 1:
            return first
        merged = cls.__new__(cls)
        nn.Module.__init__(merged)
        merged.in_features, merged.out_features = first.in_features, sum(layer.out_features for layer in layers)
        merged.out_dtype = first.out_dtype
        merged._as_merged()
        merged.bias = None if first.bias is None else torch.cat([layer.bias for layer in layers])
        with torch.no_grad():
            merged.register_buffer(cls.WEIGHT, torch.cat([getattr(layer, cls.WEIGHT) for layer in layers]))
            merged.register_buffer("weight_scale", torch.cat([layer.weight_scale for layer in layers], dim=1))
        start = 0
        for layer in layers:
            setattr(layer, cls.WEIGHT, getattr(merged, cls.WEIGHT)[start : start + layer.out_features])
            start += layer.out_features
        return merged

    def forward_cast(self, rows: CastRows, with_bias: bool = True) -> torch.Tensor:
        """`forward` of an input already quantized by `input_cast` (e.g. inside its producer);
        `with_bias=False` leaves the bias for the caller to add inside the op that reads the output."""
        values = rows.values.reshape(-1, self.in_features)
        return self._output(self._product(values, rows.scales.reshape(-1, 1)), rows.values.shape[:-1], with_bias)

    def _product(self, values: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError


def require_preset(config: QuantConfig, method: str) -> None:
    get_method(method).check_preset(method, config.preset)


def swap_linear(model: nn.Module, name: str, linear: nn.Linear, new: nn.Module) -> None:
    parent_name, _, child = name.rpartition(".")
    setattr(model.get_submodule(parent_name) if parent_name else model, child, new)
    # The report keeps the replaced layer (for its parameter count): drop its storage, keep its shape.
    linear.weight = nn.Parameter(torch.empty_like(linear.weight, device="meta"), requires_grad=False)


def _tensor_bytes(tensors) -> int:
    """Bytes of the storages behind `tensors`, each storage once."""
    return sum({t.untyped_storage().data_ptr(): t.untyped_storage().nbytes() for t in tensors if t is not None}.values())


def replace_all(model: nn.Module, selection: Selection, make, fmt: str) -> MethodResult:
    """Every selected linear replaced by `make(name, linear)`; the header's `weight_memory` records the
    replaced layers' bytes as released and as packed (weights, scales, biases), `kernels` the number of
    layers per kernel (a class's `KERNEL`, else the library's class)."""
    result = MethodResult(format=fmt)
    released = packed = 0
    kernels: dict[str, int] = {}
    for name, linear in selection.flat().items():
        released += _tensor_bytes([linear.weight, linear.bias])
        new = make(name, linear)
        packed += _tensor_bytes([*new.parameters(), *new.buffers()])
        kernel = getattr(new, "KERNEL", f"{type(new).__module__.split('.')[0]}.{type(new).__name__}")
        kernels[kernel] = kernels.get(kernel, 0) + 1
        swap_linear(model, name, linear, new)
        result.hooks[name] = CountingHook(new, InputTransform())  # counts calls, changes nothing
    result.details["weight_memory"] = {"layers": len(result.hooks), "released_bytes": released, "packed_bytes": packed,
                                       "ratio": packed / released if released else None}
    result.details["kernels"] = kernels
    return result
