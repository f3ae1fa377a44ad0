"""Real-kernel quantization methods for `quantize_`: packed weights and integer/FP8 matrix products.

Registered by name in `quant.methods` (imported when a cell first uses one):

    nf4          bitsandbytes 4-bit NormalFloat, blocks of 64, bf16 compute   (preset W4)
    int8         bitsandbytes LLM.int8(): int8 weights, fp16 outlier columns  (preset W8)
    int4wo       int4 weight-only, asymmetric groups, tinygemm kernel          (preset W4[G<g>])
                 (`torch._weight_int4pack_mm`, on the CPU `_weight_int4pack_mm_for_cpu`; AWQ's
                 INT4 GEMM format without AWQ's scale search)
    awq          activation-aware weight quantization (`quant.awq` scale search on calibration
                 rows): W4 on CUDA as int4wo with the scales, fake-quantized elsewhere (W<b>[G<g>])
    smoothquant  W8A8 int8: per-channel weights, dynamic per-token activations, `torch._int_mm`,
                 with SmoothQuant's per-channel migration vector (from calibration statistics,
                 required) folded into the weights                                           (W8A8)
    int8_dynamic W8A8 int8: the same kernel without smoothing (the int8 counterpart of fp8)  (W8A8)
    fp8          W8A8 FP8 e4m3: per-channel weights, dynamic per-token activations,
                 `torch._scaled_mm` with row-wise scales (the H100's native format)          (W8A8)
    fp8_tensor   the same with one scale per weight tensor and one per activation tensor (W8A8)
    fp8_static   FP8 with one weight scale and one static activation scale per layer, from the
                 calibration statistics' input absmax (as FP8 inference stacks serve)      (W8A8)

Each selected `nn.Linear` is replaced in its parent by a module holding the packed weight (the
bf16 weight is freed), and gets a counting pre-hook that changes nothing, so `unfired()` proves
that the kernel ran; the header's `quant_report.weight_memory` records the replaced layers' bytes as
released and as packed. bitsandbytes is an optional extra (`pip install vlaquantbench[kernels]`);
int4wo, smoothquant, int8_dynamic and fp8 need only PyTorch (fp8 needs a CUDA GPU and refuses any
other device by name before it changes a weight, since row-wise `torch._scaled_mm` runs on CUDA
GPUs of compute capability 8.9+ only; the int8 and int4 products also run on the CPU).

In pi0.5's captured sampler, `fp8` and `int8_dynamic` layers that read one input run as one product
on a merged weight (`_PerTokenLinear.merged`), their input cast to e4m3 or int8 rows by the op that
produces it (`input_cast`, `quant.grid.PerTokenCast`; `models.pi05.fast.linear_groups`); `int4wo`
layers run one by one as modules (tinygemm takes bf16 inputs: nothing to cast). Numerics (W8A8
and W4A16 alike): scales FP32; everything between the products as in a BF16 cell (norms, softmax,
residuals, the float32 SigLIP tower's arithmetic), output in the layer's dtype (bf16, or float32
for the SigLIP tower and projector). FP8: FP32 accumulation in the tensor cores (fast accumulation
on Hopper) with the scales applied by `torch._scaled_mm`. INT8: exact int32 accumulation, then
(sum * s_x) * s_w in FP32 rounded once to the output dtype (`dequantize_int32`); the int32 sums
pass through memory once (4 bytes a value, twice a bf16 output). INT4: bf16 activations, tinygemm
dequantizes the weights to bf16 and accumulates in FP32, output bf16 (the float32 SigLIP layers
take and give bf16 here, their only change besides the weights).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F  # noqa: N812
from torch import nn

from vlaquantbench.errors import UserError
from vlaquantbench.quant.apply import MethodResult, QuantConfig, layer_statistics
from vlaquantbench.quant.methods import get_method
from vlaquantbench.quant.awq import search_scales
from vlaquantbench.quant.calibration import smoothing_factors
from vlaquantbench.quant.grid import SCALE_FLOOR, CastRows, PerTokenCast, fake_quant_weight
from vlaquantbench.quant.hooks import CountingHook, InputTransform
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

    @triton.jit
    def _dequantize_rows(acc_ptr, row_scale_ptr, col_scale_ptr, out_ptr, n_cols, acc_stride, BLOCK: tl.constexpr):
        row = tl.program_id(0).to(tl.int64)
        cols = tl.program_id(1) * BLOCK + tl.arange(0, BLOCK)
        inside = cols < n_cols
        acc = tl.load(acc_ptr + row * acc_stride + cols, mask=inside, other=0).to(tl.float32)
        y = acc * tl.load(row_scale_ptr + row) * tl.load(col_scale_ptr + cols, mask=inside, other=0.0)
        tl.store(out_ptr + row * n_cols + cols, y.to(out_ptr.dtype.element_ty), mask=inside)


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


class _PackedLinear(nn.Module):
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


class _PerTokenLinear(_PackedLinear):
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
    def merged(cls, layers: list[_PerTokenLinear]) -> _PerTokenLinear:
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


# cuBLASLt's int8 products (`torch._int_mm` on CUDA) take more than 16 rows, in multiples of 8 here.
INT_MM_MIN_ROWS = 32


def dequantize_int32(acc: torch.Tensor, row_scales: torch.Tensor, col_scales: torch.Tensor,
                     dtype: torch.dtype) -> torch.Tensor:
    """(acc * row_scales) * col_scales in float32, rounded once to `dtype`: an int8 product's int32
    sums back to the layer's scale. One Triton kernel in eager CUDA code (one read of the int32
    sums, one write of the output), the same arithmetic as torch ops elsewhere."""
    if triton is None or not acc.is_cuda or torch.compiler.is_compiling():
        return (acc.float() * row_scales * col_scales).to(dtype)
    rows, cols = acc.shape
    out = torch.empty(rows, cols, dtype=dtype, device=acc.device)
    _dequantize_rows[(rows, triton.cdiv(cols, 1024))](acc, row_scales, col_scales, out, cols, acc.stride(0), BLOCK=1024)
    return out


class Int8DynamicLinear(_PerTokenLinear):
    """W8A8 int8: y = (round(x/s_x) @ W_q^T) * s_x * s_w (+ b), int32 accumulation in `torch._int_mm`
    (exact), the scales applied in float32 and the result rounded once to the layer's dtype.

    `smooth` (SmoothQuant's d) is folded into the weights and divided out of the input first; a
    layer without it takes its input cast per token by its producer (`input_cast`)."""

    WEIGHT, INPUT = "weight_int8", torch.int8
    KERNEL = "torch._int_mm (int8 x int8 -> int32) + float32 rescale"

    def __init__(self, linear: nn.Linear, smooth: torch.Tensor | None = None):
        super().__init__(linear)
        weight = linear.weight.detach().float()
        if smooth is not None:
            weight = weight * smooth
        scale = weight.abs().amax(dim=1, keepdim=True).clamp_min(1e-8) / 127.0
        self.register_buffer("weight_int8", torch.clamp(torch.round(weight / scale), -128, 127).to(torch.int8))
        self.register_buffer("weight_scale", scale.t().contiguous())  # 1 x out
        self.register_buffer("smooth", None if smooth is None else smooth.float())

    @property
    def per_token_input(self) -> bool:
        return self.smooth is None

    def _as_merged(self) -> None:
        self.register_buffer("smooth", None)

    def _matmul(self, x2d: torch.Tensor) -> torch.Tensor:
        if self.smooth is not None:
            x2d = x2d.float() / self.smooth
        return self._product(*quantize_per_token(x2d, torch.int8))

    def _product(self, values: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
        rows = values.shape[0]
        padded = max(INT_MM_MIN_ROWS, (rows + 7) // 8 * 8)
        if padded != rows:
            values = F.pad(values, (0, 0, 0, padded - rows))
        acc = torch._int_mm(values, self.weight_int8.t())[:rows]
        return dequantize_int32(acc, scales, self.weight_scale, self.out_dtype)


class Fp8DynamicLinear(_PerTokenLinear):
    """W8A8 FP8 e4m3 with per-output-channel weight scales and per-token activation scales, or with
    one scale per tensor for each (`tensorwise`)."""

    WEIGHT, INPUT = "weight_fp8", FP8
    KERNEL = "torch._scaled_mm (e4m3 x e4m3, FP32 scales)"

    def __init__(self, linear: nn.Linear, tensorwise: bool = False):
        super().__init__(linear)
        weight = linear.weight.detach().float()
        self.tensorwise = tensorwise
        amax = weight.abs().amax() if tensorwise else weight.abs().amax(dim=1, keepdim=True)
        scale = amax.clamp_min(1e-12) / FP8_MAX
        self.register_buffer("weight_fp8", (weight / scale).clamp(-FP8_MAX, FP8_MAX).to(FP8))
        self.register_buffer("weight_scale", scale.reshape(1, -1).contiguous())  # 1 x out (or 1 x 1), float32

    @property
    def per_token_input(self) -> bool:
        return not self.tensorwise

    def _as_merged(self) -> None:
        self.tensorwise = False

    def _quantize_input(self, x2d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        if not self.tensorwise:
            return quantize_per_token(x2d, FP8)
        # One global amax, then one pass: dividing by the float32 scale promotes x inside the
        # kernel (no float32 copy of x first); under `torch.compile` both fuse into x's producer.
        scale = (x2d.abs().amax().float().clamp_min(SCALE_FLOOR) / FP8_MAX).reshape(1, 1)
        return torch.div(x2d, scale).clamp_(-FP8_MAX, FP8_MAX).to(FP8), scale

    def _matmul(self, x2d: torch.Tensor) -> torch.Tensor:
        return self._product(*self._quantize_input(x2d))

    def _product(self, x_fp8: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
        # Fast accumulation (Hopper's FP8 tensor-core accumulator without periodic FP32 promotion),
        # as FP8 inference stacks use it: 8.0 instead of 9.9 ms of GEMMs on the LLaMA benchmark.
        return torch._scaled_mm(x_fp8, self.weight_fp8.t(), scale_a=scale, scale_b=self.weight_scale,
                                out_dtype=self.out_dtype, use_fast_accum=x_fp8.is_cuda)


class Fp8StaticLinear(Fp8DynamicLinear):
    """W8A8 FP8 e4m3 with one weight scale and one static activation scale per layer, calibrated:
    the largest |x| the layer saw during calibration / 448. Quantizing the input is then one
    divide, clamp and cast with no reduction, which `torch.compile` fuses into the op producing
    the input; inputs beyond the calibrated range saturate at +-448 (the e4m3 maximum)."""

    def __init__(self, linear: nn.Linear, input_absmax: torch.Tensor):
        super().__init__(linear, tensorwise=True)
        scale = input_absmax.float().amax().clamp_min(SCALE_FLOOR) / FP8_MAX
        self.register_buffer("input_scale", scale.reshape(1, 1).to(linear.weight.device))

    def _quantize_input(self, x2d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return torch.div(x2d, self.input_scale).clamp_(-FP8_MAX, FP8_MAX).to(FP8), self.input_scale


class Int4WeightOnlyLinear(_PackedLinear):
    """int4 weights in asymmetric groups along the input, bf16 activations, PyTorch's tinygemm kernel
    (`torch._weight_int4pack_mm` on CUDA, `torch._weight_int4pack_mm_for_cpu` on the CPU).

    tinygemm dequantizes w = (q - 8) * scale + zero, so zero = min + 8 * scale for q in 0..15. Its
    packing takes an input size that is a multiple of 128 and of the group: a layer whose input is
    not (SigLIP's fc2 reads 4,304 values, pi0.5's action_in_proj 32) gets zero weight columns up to
    the next multiple, and its input zeros in the same columns (one copy of the input per call), so
    the product is unchanged; its last group's range then also spans 0."""

    INNER_K_TILES = 8
    KERNEL = "torch._weight_int4pack_mm (tinygemm: int4 weights, bf16 activations)"

    def __init__(self, linear: nn.Linear, group_size: int):
        super().__init__(linear)
        out_features, in_features = linear.weight.shape
        rows_multiple = 8 if linear.weight.is_cuda else 16  # tinygemm's packing, on CUDA and on the CPU
        if out_features % rows_multiple:
            raise UserError(f"int4wo: out_features {out_features} is not a multiple of {rows_multiple} "
                            f"(tinygemm's packing on {linear.weight.device.type})")
        multiple = max(self.INNER_K_TILES * 16, group_size)
        self.padded_in = -(-in_features // multiple) * multiple
        weight = F.pad(linear.weight.detach().float(), (0, self.padded_in - in_features))
        weight = weight.reshape(out_features, -1, group_size)
        low = weight.amin(dim=-1, keepdim=True)
        scale = ((weight.amax(dim=-1, keepdim=True) - low) / 15.0).clamp_min(1e-6)
        q = torch.clamp(torch.round((weight - low) / scale), 0, 15).reshape(out_features, self.padded_in)
        if linear.weight.is_cuda:
            packed = (q[:, ::2].to(torch.uint8) << 4 | q[:, 1::2].to(torch.uint8)).contiguous()
            self.register_buffer("weight_int4", torch._convert_weight_to_int4pack(packed, self.INNER_K_TILES))
        else:
            self.register_buffer("weight_int4", torch._convert_weight_to_int4pack_for_cpu(q.to(torch.int32),
                                                                                          self.INNER_K_TILES))
        zero = low + 8.0 * scale
        scales_zeros = torch.stack([scale.squeeze(-1), zero.squeeze(-1)], dim=-1)  # out x groups x 2
        self.register_buffer("scales_and_zeros", scales_zeros.transpose(0, 1).contiguous().to(torch.bfloat16))
        self.group_size = group_size

    def _matmul(self, x2d: torch.Tensor) -> torch.Tensor:
        x2d = F.pad(x2d.to(torch.bfloat16), (0, self.padded_in - self.in_features))
        product = torch._weight_int4pack_mm if x2d.is_cuda else torch._weight_int4pack_mm_for_cpu
        return product(x2d, self.weight_int4, self.group_size, self.scales_and_zeros)


def _bnb_linear(linear: nn.Linear, kind: str) -> nn.Module:
    try:
        import bitsandbytes as bnb
    except ImportError as err:
        raise UserError(f"method {kind!r} needs bitsandbytes: pip install 'vlaquantbench[kernels]'") from err
    device = linear.weight.device
    has_bias = linear.bias is not None
    if kind == "nf4":
        module = bnb.nn.Linear4bit(linear.in_features, linear.out_features, bias=has_bias,
                                   compute_dtype=torch.bfloat16, quant_type="nf4", device="meta")
        module.weight = bnb.nn.Params4bit(linear.weight.detach(), requires_grad=False, quant_type="nf4")
    else:
        module = bnb.nn.Linear8bitLt(linear.in_features, linear.out_features, bias=has_bias,
                                     has_fp16_weights=False, threshold=6.0, device="meta")
        module.weight = bnb.nn.Int8Params(linear.weight.detach(), requires_grad=False, has_fp16_weights=False)
    if has_bias:
        module.bias = nn.Parameter(linear.bias.detach(), requires_grad=False)
    return module.to(device)  # bitsandbytes quantizes on the move to a CUDA device


def _require(config: QuantConfig, method: str) -> None:
    get_method(method).check_preset(method, config.preset)


def _swap(model: nn.Module, name: str, linear: nn.Linear, new: nn.Module) -> None:
    parent_name, _, child = name.rpartition(".")
    setattr(model.get_submodule(parent_name) if parent_name else model, child, new)
    # The report keeps the replaced layer (for its parameter count): drop its storage, keep its shape.
    linear.weight = nn.Parameter(torch.empty_like(linear.weight, device="meta"), requires_grad=False)


def _tensor_bytes(tensors) -> int:
    """Bytes of the storages behind `tensors`, each storage once."""
    return sum({t.untyped_storage().data_ptr(): t.untyped_storage().nbytes() for t in tensors if t is not None}.values())


def _replace_all(model: nn.Module, selection: Selection, make, fmt: str) -> MethodResult:
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
        _swap(model, name, linear, new)
        result.hooks[name] = CountingHook(new, InputTransform())  # counts calls, changes nothing
    result.details["weight_memory"] = {"layers": len(result.hooks), "released_bytes": released, "packed_bytes": packed,
                                       "ratio": packed / released if released else None}
    result.details["kernels"] = kernels
    return result


def nf4(model, selection, config):
    _require(config, "nf4")
    return _replace_all(model, selection, lambda n, m: _bnb_linear(m, "nf4"),
                        "bitsandbytes NF4 (4-bit NormalFloat, block 64, bf16 compute)")


def llm_int8(model, selection, config):
    _require(config, "int8")
    return _replace_all(model, selection, lambda n, m: _bnb_linear(m, "int8"),
                        "bitsandbytes LLM.int8() (int8 row-wise weights, fp16 outlier columns above 6.0)")


def int4_weight_only(model, selection, config):
    _require(config, "int4wo")
    group = config.preset.weight.group_size or 128
    return _replace_all(model, selection, lambda n, m: Int4WeightOnlyLinear(m, group),
                        f"int4 weight-only, asymmetric group {group}, tinygemm (torch._weight_int4pack_mm), bf16 activations")


def int8_dynamic(model, selection, config):
    """W8A8 int8 without smoothing: the int8 counterpart of `fp8` (in pi0.5's captured sampler the
    producing op casts the input rows, and q/k/v and gate/up run as one product)."""
    _require(config, "int8_dynamic")
    return _replace_all(model, selection, lambda n, m: Int8DynamicLinear(m),
                        "W8A8 int8 (per-channel weights, dynamic per-token activations, torch._int_mm, "
                        "int32 accumulation, float32 rescale)")



def _int4_kernel_fits(linear: nn.Linear, grid) -> bool:
    """tinygemm packs 4-bit asymmetric groups of 32..256 with K a multiple of 128, N of 8, on CUDA."""
    return (linear.weight.is_cuda and grid.bits == 4 and not grid.symmetric and grid.group_size in (32, 64, 128, 256)
            and linear.in_features % max(128, grid.group_size) == 0 and linear.out_features % 8 == 0)


def awq(model, selection, config):
    """AWQ: per layer, the `quant.awq` scale search on the calibration rows, then Q(W diag(s)) with
    an input hook dividing by s. W4 asymmetric groups on CUDA use the int4wo tinygemm kernel
    (its grid spans [min, max] of each group, not the zero-including range of `quant.grid`)."""
    _require(config, "awq")
    grid = config.preset.weight
    stats = layer_statistics(selection, config, "awq", "AWQ calibration statistics (mean |x| and sampled input rows)",
                         "collect them on the unquantized policy with quant.calibration.observe(layers, "
                         "sample_rows=128) and pass stats=... (the runner's calibrate step does this for awq cells)",
                         usable=lambda layer: layer.samples is not None)
    fmt = f"awq-int{grid.bits}-" + (f"g{grid.group_size}" if grid.group_size else "channel")
    hooks, alphas, rows, error_ratios, kernel_layers = {}, [], [], [], 0
    for name, linear in selection.flat().items():
        absmean, samples = stats[name].absmean, stats[name].samples
        search = search_scales(linear.weight, absmean, samples, grid.bits, grid.group_size, grid.symmetric)
        with torch.no_grad():
            scaled = (linear.weight.float() * search.scales).to(linear.weight.dtype)
            if _int4_kernel_fits(linear, grid):
                linear.weight.copy_(scaled)
                target = Int4WeightOnlyLinear(linear, grid.group_size)
                _swap(model, name, linear, target)
                kernel_layers += 1
            else:
                linear.weight.copy_(fake_quant_weight(scaled, grid.bits, grid.group_size, grid.symmetric))
                target = linear
        hooks[name] = CountingHook(target, InputTransform(smooth=search.scales))
        alphas.append(search.alpha)
        rows.append(samples.shape[0])
        error_ratios.append(search.error / search.rtn_error if search.rtn_error > 0 else 1.0)
    described = (
        f"{fmt}: activation-aware scales (alpha grid 0..1 step 0.05 on calibration rows), weights "
        f"{grid.describe()}; {kernel_layers} layers on tinygemm (torch._weight_int4pack_mm), "
        f"{len(hooks) - kernel_layers} fake-quantized"
    )
    details = {
        "format": fmt,
        "alpha_histogram": {f"{a:.2f}": alphas.count(a) for a in sorted(set(alphas))},
        "alpha_mean": sum(alphas) / len(alphas) if alphas else None,
        "calibration_rows": {"min": min(rows, default=0), "max": max(rows, default=0)},
        # mean over layers of E(alpha*) / E(0) on the calibration rows (1.0: no gain over RTN)
        "error_vs_rtn_mean": sum(error_ratios) / len(error_ratios) if error_ratios else None,
        "kernel_layers": kernel_layers,
        "stats_cache": f"{config.stats.key}.pt" if config.stats is not None else None,
    }
    return MethodResult(format=described, hooks=hooks, calibrated=set(hooks), details={"awq": details})


def smoothquant(model, selection, config):
    """SmoothQuant W8A8: migrate activation outliers into the weights with d_j = a_j^alpha / w_j^(1-alpha)
    (`quant.calibration.smoothing_factors`), then int8 per-channel weights and per-token inputs.
    Layers of components the calibration does not cover (the pi models' projector) run unsmoothed."""
    _require(config, "smoothquant")
    if config.calibration is None or config.calibration.alpha is None:
        raise UserError("method 'smoothquant' smooths by definition: pass calibration=CalibrationSettings(alpha=...) "
                        "and stats=... (the runner's calibrate step collects them for smoothquant cells)")
    smoothed = set()

    def make(name, linear):
        stats = config.stats.layers.get(name) if selection.component_of(name) in config.calibration.components else None
        if stats is None:
            return Int8DynamicLinear(linear)
        smoothed.add(name)
        return Int8DynamicLinear(linear, smoothing_factors(stats.absmax, linear.weight, config.calibration.alpha))

    result = _replace_all(model, selection, make,
                          "W8A8 int8 (per-channel weights, dynamic per-token activations, torch._int_mm), SmoothQuant "
                          f"migration alpha={config.calibration.alpha} from rollout calibration statistics "
                          f"(cache {config.stats.key}; not the paper's 512 text samples)")
    result.calibrated = smoothed
    return result


def _require_rowwise_fp8(selection: Selection, method: str) -> None:
    """UserError, before any weight changes, unless every selected layer is on a CUDA GPU with FP8
    tensor cores: `torch._scaled_mm` with row-wise scales runs nowhere else (on the CPU, PyTorch
    2.11 scales only per tensor)."""
    for name, linear in selection.flat().items():
        device = linear.weight.device
        if device.type != "cuda" or torch.cuda.get_device_capability(device) < (8, 9):
            where = device.type if device.type != "cuda" else f"{device} ({torch.cuda.get_device_name(device)})"
            raise UserError(f"method {method!r} runs real FP8 kernels (torch._scaled_mm, row-wise scales), which need "
                            f"a CUDA GPU of compute capability 8.9 or newer (Ada, Hopper); layer {name!r} is on {where}. "
                            "Run the cell on such a GPU, or fake-quantize the same format with preset FP8E4M3 "
                            "(method rtn)")


def fp8(model, selection, config):
    _require(config, "fp8")
    _require_rowwise_fp8(selection, "fp8")
    return _replace_all(model, selection, lambda n, m: Fp8DynamicLinear(m),
                        "W8A8 FP8 e4m3 (per-channel weights, dynamic per-token activations, torch._scaled_mm row-wise, fast accumulation)")


def fp8_tensorwise(model, selection, config):
    _require(config, "fp8_tensor")
    return _replace_all(model, selection, lambda n, m: Fp8DynamicLinear(m, tensorwise=True),
                        "W8A8 FP8 e4m3 (one weight scale, one dynamic activation scale per call, torch._scaled_mm, fast accumulation)")


def fp8_static(model, selection, config):
    """FP8 W8A8 with static activation scales from the calibration statistics' per-channel absmax."""
    _require(config, "fp8_static")
    layers = layer_statistics(selection, config, "fp8_static", "calibration statistics (input absmax)",
                          "observe them on the unquantized policy with quant.calibration.observe(layers) "
                          "and pass stats=...")
    result = _replace_all(model, selection, lambda n, m: Fp8StaticLinear(m, layers[n].absmax),
                          "W8A8 FP8 e4m3 (one weight scale, one static calibrated activation scale per layer, "
                          "torch._scaled_mm, fast accumulation)")
    result.calibrated = set(result.hooks)
    return result

