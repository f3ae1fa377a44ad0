"""RTN grids and presets against a direct, element-by-element transcription of the paper's formulas
(appendix `app:quant-prelim`)."""

import math

import pytest
import torch

from vlaquantbench.errors import UserError
from vlaquantbench.quant.grid import fake_quant_activation, fake_quant_asym, fake_quant_sym, fake_quant_weight
from vlaquantbench.quant.presets import FORMATS, WeightGrid, parse_preset


def round_half_even(v: float) -> float:
    return float(round(v))  # Python's round is banker's rounding, like torch.round


def reference_sym(group: list[float], bits: int) -> list[float]:
    q_max = 2 ** (bits - 1) - 1
    s = max(max(abs(v) for v in group), 1e-8) / q_max
    s = float(torch.tensor(s, dtype=torch.float32))
    return [s * min(max(round_half_even(v / s), -(q_max + 1)), q_max) for v in group]


def reference_asym(group: list[float], bits: int) -> list[float]:
    levels = 2**bits - 1
    m, big_m = min(min(group), 0.0), max(max(group), 0.0)
    s = float(torch.tensor(max((big_m - m) / levels, 1e-8), dtype=torch.float32))
    z = min(max(round_half_even(-m / s), 0), levels)
    return [s * (min(max(round_half_even(v / s) + z, 0), levels) - z) for v in group]


def reference_weight(w: torch.Tensor, bits: int, group: int | None, sym: bool) -> torch.Tensor:
    quant = reference_sym if sym else reference_asym
    rows = []
    for row in w.tolist():
        size = group or len(row)
        out = []
        for start in range(0, len(row), size):
            out += quant(row[start : start + size], bits)
        rows.append(out)
    return torch.tensor(rows, dtype=torch.float32)


@pytest.mark.parametrize("bits", [2, 3, 4, 8])
@pytest.mark.parametrize("sym", [True, False])
def test_random_groups_match_formulas(bits, sym):
    w = torch.randn(6, 40, generator=torch.Generator().manual_seed(bits)) * 3
    got = fake_quant_weight(w, bits, 16, sym)  # 40 = 16 + 16 + short final group of 8
    torch.testing.assert_close(got, reference_weight(w, bits, 16, sym), rtol=1e-6, atol=1e-6)


def test_short_final_group_has_its_own_scale():
    w = torch.cat([torch.full((1, 8), 100.0), torch.tensor([[0.1, -0.2, 0.3]])], dim=1)
    got = fake_quant_weight(w, 4, 8, symmetric=True)
    # With a shared scale (100/7) the small tail would round to 0; its own scale keeps it.
    assert torch.all(got[0, 8:] != 0)
    torch.testing.assert_close(got, reference_weight(w, 4, 8, True))


@pytest.mark.parametrize("sym", [True, False])
def test_constant_group(sym):
    w = torch.full((2, 8), 0.37)
    got = fake_quant_weight(w, 3, None, sym)
    torch.testing.assert_close(got, reference_weight(w, 3, None, sym))
    torch.testing.assert_close(got, w, rtol=0, atol=1e-6)  # the range includes zero: 0.37 is a grid point
    zeros = torch.zeros(2, 8)
    assert torch.equal(fake_quant_weight(zeros, 3, None, sym), zeros)  # scale floor, no NaN


@pytest.mark.parametrize("values", [[0.5, 1.0, 2.0, 3.5], [-0.5, -1.0, -2.0, -3.5]])
def test_single_sign_group(values):
    x = torch.tensor([values])
    torch.testing.assert_close(fake_quant_asym(x, 2), torch.tensor([reference_asym(values, 2)]))
    torch.testing.assert_close(fake_quant_sym(x, 2), torch.tensor([reference_sym(values, 2)]))


def test_ties_round_to_even():
    # scale = 7/7 = 1: 0.5 -> 0, 1.5 -> 2, 2.5 -> 2, -0.5 -> 0, -2.5 -> -2 (nearest even)
    x = torch.tensor([[0.5, 1.5, 2.5, -0.5, -2.5, 7.0]])
    got = fake_quant_sym(x, 4)
    assert got.tolist() == [[0.0, 2.0, 2.0, 0.0, -2.0, 7.0]]
    assert got.tolist() == [reference_sym(x[0].tolist(), 4)]


def test_float32_math_and_dtype_roundtrip():
    w = torch.randn(4, 256, generator=torch.Generator().manual_seed(1)).to(torch.bfloat16)
    got = fake_quant_weight(w, 4, 128, symmetric=False)
    assert got.dtype == torch.bfloat16
    expected = reference_weight(w.float(), 4, 128, False).to(torch.bfloat16)
    torch.testing.assert_close(got, expected, rtol=0, atol=0)


def test_activation_is_per_token_over_last_dim():
    x = torch.randn(2, 3, 16, generator=torch.Generator().manual_seed(2))
    x[0, 1] *= 1000  # one loud token must not change the others' scales
    got = fake_quant_activation(x, 4)
    for b in range(2):
        for t in range(3):
            assert got[b, t].tolist() == pytest.approx(reference_sym(x[b, t].tolist(), 4), rel=1e-6, abs=1e-6)


@pytest.mark.parametrize(
    "name, bits, group, sym, act",
    [
        ("W2", 2, 128, False, None),
        ("W3", 3, 128, False, None),
        ("W4", 4, 128, False, None),
        ("W8", 8, None, True, None),
        ("W4A4", 4, 128, False, 4),
        ("W4A5", 4, 128, False, 5),
        ("W4A6", 4, 128, False, 6),
        ("W4A8", 4, 128, False, 8),
        ("W8A8", 8, None, True, 8),
        ("W3G64ASYM", 3, 64, False, None),
        ("W4G0SYM", 4, None, True, None),
        ("W3G32", 3, 32, False, None),
        ("W4G128SYM", 4, 128, True, None),
    ],
)
def test_presets(name, bits, group, sym, act):
    preset = parse_preset(name)
    assert (preset.weight.bits, preset.weight.group_size, preset.weight.symmetric, preset.act_bits) == (
        bits, group, sym, act)


@pytest.mark.parametrize(
    "name,weight,acts",
    [
        ("MXFP4", "MXFP4", "MXFP4"),
        ("NVFP4", "NVFP4", "NVFP4"),
        ("FP8E4M3", "FP8E4M3", "FP8E4M3"),
        ("FP8E5M2PT", "FP8E5M2PT", "FP8E5M2PT"),
        ("MXFP6E2M3", "MXFP6E2M3", "MXFP6E2M3"),
        ("W4AMXFP4", WeightGrid(4, 128, False), "MXFP4"),
        ("W8AMXFP8E4M3", WeightGrid(8, None, True), "MXFP8E4M3"),
        ("WMXFP4", "MXFP4", None),
        ("WNVFP4A8", "NVFP4", 8),
    ],
)
def test_float_format_presets(name, weight, acts):
    preset = parse_preset(name)
    assert preset.weight == (FORMATS[weight] if isinstance(weight, str) else weight)
    if isinstance(acts, str):
        assert preset.act_format == FORMATS[acts] and preset.act_bits is None
    else:
        assert preset.act_format is None and preset.act_bits == acts
    assert preset.quantizes_activations == (acts is not None) and not preset.is_baseline


@pytest.mark.parametrize("bad", ["MXFP8", "MXFP6", "FP8", "WMXFP4G64", "WMXFP4SYM", "MXFP4A4", "FP4", "W4AFP8"])
def test_malformed_float_presets_name_the_formats(bad):
    with pytest.raises(UserError, match="MXFP4, NVFP4") as err:
        parse_preset(bad)
    assert repr(bad) in str(err.value)


def test_baseline_preset_quantizes_nothing():
    assert parse_preset("BASELINE").is_baseline


@pytest.mark.parametrize("bad", ["W4X", "w4", "A4", "W9", "W4A1", "W4G", "INT4"])
def test_unknown_preset_lists_valid_forms(bad):
    with pytest.raises(UserError, match=r"W<b>\[G<g>\]\[A<a>\]\[SYM\|ASYM\]") as err:
        parse_preset(bad)
    assert repr(bad) in str(err.value) and "W4A8" in str(err.value)


def test_reference_transcription_is_not_vacuous():
    # guard: the transcription itself must quantize (4 distinct levels for 2-bit asym)
    out = reference_asym([0.0, 0.1, 0.5, 0.9, 1.0], 2)
    assert len(set(out)) <= 4 and not math.isclose(out[1], 0.1)
