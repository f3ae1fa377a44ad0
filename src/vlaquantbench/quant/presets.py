"""Quantization presets (paper `tab:quant_presets`, plus floating-point formats) and the preset grammar.

    preset   BASELINE | <format> | W<weights>[A<acts>][SYM|ASYM]
    weights  <b>[G<g>] | <format>              acts  <a> | <format>
    format   FP8E4M3 | FP8E5M2 | FP8E4M3PT | FP8E5M2PT | MXFP8E4M3 | MXFP8E5M2
             | MXFP6E3M2 | MXFP6E2M3 | MXFP4 | NVFP4

    e.g. W4, W4A8, W3G64ASYM, W4G0SYM, MXFP4, NVFP4, FP8E4M3, W4AMXFP4, WMXFP4, WNVFP4A8

Integer weight grids (`W<b>`) default to the paper's convention for the bit width: asymmetric with
groups of 128 below 8 bits, symmetric per output channel at 8 bits. `G<g>` overrides the group size
(`G0` means per output channel) and `SYM`/`ASYM` the symmetry; both apply to integer weights only.
`A<a>` adds dynamic symmetric per-token activation quantization with a bits. A bare `<format>`
quantizes weights (static, in place) and linear inputs (dynamic, per call) in that format;
`W<format>` and `A<format>` use it for one side only. `BASELINE` quantizes nothing.

Formats (grids in `quant.float_grid`):
    FP8E4M3, FP8E5M2      FP8; weights one scale per output channel, inputs one per token
    FP8E4M3PT, FP8E5M2PT  FP8; one scale per weight tensor, one per input sample (dim 0)
    MXFP8E4M3 ... MXFP4   OCP MX v1.0: blocks of 32 along the input dimension, shared E8M0 scale
    NVFP4                 E2M1 in blocks of 16, E4M3 block scale x FP32 scale of the weight
                          tensor / of each input sample (dim 0)
A "per tensor" activation scale is computed per sample of the batch (dim 0, one episode's input
to the layer) so that an episode's actions do not depend on which episodes share its batch.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import TYPE_CHECKING

from vlaquantbench.errors import UserError

if TYPE_CHECKING:  # the grids need torch; the grammar does not (the workflow parses presets without it)
    import torch

DEFAULT_GROUP_SIZE = 128
BIT_RANGE = range(2, 9)
NAMED_PRESETS = ("BASELINE", "W2", "W3", "W4", "W8", "W4A4", "W4A5", "W4A6", "W4A8", "W8A8")


@dataclass(frozen=True)
class WeightGrid:
    """Integer RTN weight grid (`quant.grid`)."""

    bits: int
    group_size: int | None  # None: one scale per output channel
    symmetric: bool

    def describe(self) -> str:
        kind = "symmetric" if self.symmetric else "asymmetric"
        return f"{self.bits}-bit {kind}, " + (f"group {self.group_size}" if self.group_size else "per channel")

    def quantize_weight(self, weight: torch.Tensor) -> torch.Tensor:
        from vlaquantbench.quant.grid import fake_quant_weight

        return fake_quant_weight(weight, self.bits, self.group_size, self.symmetric)


@dataclass(frozen=True)
class FloatFormat:
    """A floating-point format for weights and linear inputs: `fp8` (per channel or per tensor
    scale), `mx` (OCP MX blocks of 32) or `nvfp4` (E2M1 blocks of 16, two-level scale)."""

    name: str
    family: str  # "fp8" | "mx" | "nvfp4"
    element: str  # element format, a key of `quant.float_grid.ELEMENTS` (looked up on use)
    per_tensor: bool = False  # fp8 only

    def _grid(self):
        from vlaquantbench.quant import float_grid

        return float_grid, float_grid.ELEMENTS[self.element]

    def describe(self, role: str) -> str:
        """The exact format, for `role` "weights" (static) or "activations" (dynamic)."""
        grid, _ = self._grid()
        weights = role == "weights"
        if self.family == "fp8":
            if self.per_tensor:
                scope = "one scale per tensor" if weights else "one dynamic scale per sample"
            else:
                scope = "one scale per output channel" if weights else "one dynamic scale per token"
            return f"{self.name}: FP8 {self.element}, {scope}, saturating RNE"
        if self.family == "mx":
            return (f"{self.name}: OCP MX v1.0, {self.element} elements in blocks of {grid.MX_BLOCK} along the "
                    "input dimension, shared E8M0 scale (floor rule), saturating RNE")
        tensor = "per weight tensor" if weights else "per sample, dynamic"
        return (f"{self.name}: E2M1 elements in blocks of {grid.NVFP4_BLOCK} along the input dimension, E4M3 block "
                f"scale x FP32 scale ({tensor}), saturating RNE")

    def quantize_weight(self, weight: torch.Tensor) -> torch.Tensor:
        grid, element = self._grid()
        if self.family == "fp8":
            return grid.fake_quant_fp8(weight, element, per_row=not self.per_tensor)
        if self.family == "mx":
            return grid.fake_quant_mx(weight, element)
        return grid.fake_quant_nvfp4(weight)

    def quantize_activation(self, x: torch.Tensor) -> torch.Tensor:
        grid, element = self._grid()
        if self.family == "mx":
            return grid.fake_quant_mx(x, element)
        if self.family == "fp8" and not self.per_tensor:
            return grid.fake_quant_fp8(x, element, per_row=True)
        if x.dim() < 2:  # one sample: its scale is the tensor's
            return self.quantize_weight(x)
        if self.family == "fp8":  # one scale per sample = one per row of the flattened samples
            return grid.fake_quant_fp8(x.reshape(x.shape[0], -1), element, per_row=True).reshape(x.shape)
        return grid.fake_quant_nvfp4(x, x.float().abs().amax(dim=tuple(range(1, x.dim())), keepdim=True))


FORMATS = {
    f.name: f
    for f in (
        FloatFormat("FP8E4M3", "fp8", "E4M3"),
        FloatFormat("FP8E5M2", "fp8", "E5M2"),
        FloatFormat("FP8E4M3PT", "fp8", "E4M3", per_tensor=True),
        FloatFormat("FP8E5M2PT", "fp8", "E5M2", per_tensor=True),
        FloatFormat("MXFP8E4M3", "mx", "E4M3"),
        FloatFormat("MXFP8E5M2", "mx", "E5M2"),
        FloatFormat("MXFP6E3M2", "mx", "E3M2"),
        FloatFormat("MXFP6E2M3", "mx", "E2M3"),
        FloatFormat("MXFP4", "mx", "E2M1"),
        FloatFormat("NVFP4", "nvfp4", "E2M1"),
    )
}
_FORMAT = "|".join(sorted(FORMATS, key=len, reverse=True))
_GRAMMAR = re.compile(
    rf"(?P<bare>{_FORMAT})"
    rf"|W(?:(?P<wf>{_FORMAT})|(?P<w>\d+)(?:G(?P<g>\d+))?)(?:A(?:(?P<af>{_FORMAT})|(?P<a>\d+)))?(?P<sym>SYM|ASYM)?"
)


@dataclass(frozen=True)
class Preset:
    name: str
    weight: WeightGrid | FloatFormat | None
    act_bits: int | None  # integer per-token activation bits; None: no integer activation grid
    act_format: FloatFormat | None = None  # floating-point activation format (exclusive with act_bits)

    @property
    def is_baseline(self) -> bool:
        return self.weight is None and self.act_bits is None and self.act_format is None

    @property
    def quantizes_activations(self) -> bool:
        return self.act_bits is not None or self.act_format is not None

    def describe(self) -> str:
        """Weights and activations in words, exactly (the header's `quant_format` builds on it)."""
        if self.weight is None:
            weights = "weights released precision"
        elif isinstance(self.weight, FloatFormat):
            weights = f"weights {self.weight.describe('weights')}"
        else:
            weights = f"weights {self.weight.describe()}"
        if self.act_format is not None:
            acts = f"activations {self.act_format.describe('activations')}"
        elif self.act_bits is not None:
            acts = f"activations {self.act_bits}-bit symmetric per token"
        else:
            acts = "activations released precision"
        return f"{weights}; {acts}"


def parse_preset(name: str) -> Preset:
    """The preset called `name`; UserError naming the valid forms when it is not one."""
    if name == "BASELINE":
        return Preset(name, None, None)
    match = _GRAMMAR.fullmatch(name)
    if match is None:
        raise _unknown(name)
    if match["bare"]:
        fmt = FORMATS[match["bare"]]
        return Preset(name, fmt, None, fmt)
    act_bits = int(match["a"]) if match["a"] else None
    act_format = FORMATS[match["af"]] if match["af"] else None
    if act_bits is not None and act_bits not in BIT_RANGE:
        raise _unknown(name, f"bit widths must lie in {BIT_RANGE.start}..{BIT_RANGE.stop - 1}")
    if match["wf"]:
        if match["sym"]:
            raise _unknown(name, "SYM/ASYM apply to integer weight grids only")
        return Preset(name, FORMATS[match["wf"]], act_bits, act_format)
    bits = int(match["w"])
    if bits not in BIT_RANGE:
        raise _unknown(name, f"bit widths must lie in {BIT_RANGE.start}..{BIT_RANGE.stop - 1}")
    per_channel_default = bits >= 8
    if match["g"] is None:
        group_size = None if per_channel_default else DEFAULT_GROUP_SIZE
    else:
        group_size = int(match["g"]) or None
    symmetric = per_channel_default if match["sym"] is None else match["sym"] == "SYM"
    return Preset(name, WeightGrid(bits, group_size, symmetric), act_bits, act_format)


def _unknown(name: str, reason: str | None = None) -> UserError:
    detail = f" ({reason})" if reason else ""
    return UserError(
        f"unknown quantization preset {name!r}{detail}; valid forms: {', '.join(NAMED_PRESETS)}, "
        "W<b>[G<g>][A<a>][SYM|ASYM] (e.g. W3G64ASYM, W4G0SYM; G0 = per output channel), "
        f"a float format ({', '.join(FORMATS)}) alone, or as W<format> / A<format> (e.g. W4AMXFP4, WNVFP4A8)"
    )
