"""Quantization presets (paper `tab:quant_presets`) and the preset grammar.

    W<b>[G<g>][A<a>][SYM|ASYM]      e.g. W4, W4A8, W3G64ASYM, W4G0SYM, W3G32

Weight grids default to the paper's convention for the bit width: asymmetric with groups of 128
below 8 bits, symmetric per output channel at 8 bits. `G<g>` overrides the group size (`G0` means
per output channel) and `SYM`/`ASYM` the symmetry. `A<a>` adds dynamic symmetric per-token
activation quantization with a bits. `BASELINE` quantizes nothing.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from vlaquantbench.errors import UserError

DEFAULT_GROUP_SIZE = 128
BIT_RANGE = range(2, 9)
NAMED_PRESETS = ("BASELINE", "W2", "W3", "W4", "W8", "W4A4", "W4A5", "W4A6", "W4A8", "W8A8")

_GRAMMAR = re.compile(r"W(?P<w>\d+)(?:G(?P<g>\d+))?(?:A(?P<a>\d+))?(?P<sym>SYM|ASYM)?")


@dataclass(frozen=True)
class WeightGrid:
    bits: int
    group_size: int | None  # None: one scale per output channel
    symmetric: bool

    def describe(self) -> str:
        kind = "symmetric" if self.symmetric else "asymmetric"
        return f"{self.bits}-bit {kind}, " + (f"group {self.group_size}" if self.group_size else "per channel")


@dataclass(frozen=True)
class Preset:
    name: str
    weight: WeightGrid | None
    act_bits: int | None  # None: activations stay at released precision

    @property
    def is_baseline(self) -> bool:
        return self.weight is None and self.act_bits is None


def parse_preset(name: str) -> Preset:
    """The preset called `name`; UserError naming the valid forms when it is not one."""
    if name == "BASELINE":
        return Preset(name, None, None)
    match = _GRAMMAR.fullmatch(name)
    if match is None:
        raise _unknown(name)
    bits = int(match["w"])
    act_bits = int(match["a"]) if match["a"] else None
    if bits not in BIT_RANGE or (act_bits is not None and act_bits not in BIT_RANGE):
        raise _unknown(name, f"bit widths must lie in {BIT_RANGE.start}..{BIT_RANGE.stop - 1}")
    per_channel_default = bits >= 8
    if match["g"] is None:
        group_size = None if per_channel_default else DEFAULT_GROUP_SIZE
    else:
        group_size = int(match["g"]) or None
    symmetric = per_channel_default if match["sym"] is None else match["sym"] == "SYM"
    return Preset(name, WeightGrid(bits, group_size, symmetric), act_bits)


def _unknown(name: str, reason: str | None = None) -> UserError:
    detail = f" ({reason})" if reason else ""
    return UserError(
        f"unknown quantization preset {name!r}{detail}; valid forms: {', '.join(NAMED_PRESETS)}, "
        "or W<b>[G<g>][A<a>][SYM|ASYM] (e.g. W3G64ASYM, W4G0SYM; G0 = per output channel)"
    )
