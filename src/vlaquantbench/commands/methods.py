"""`vqb methods`: the quantization methods a cell name can use (`quant.methods.METHODS`), with the
presets each implements, the calibration statistics its cells collect, the transforms it applies
first, its options and whether it runs inside a captured CUDA graph. No torch import."""

from __future__ import annotations

import argparse
import dataclasses
import json

from vlaquantbench.quant.methods import INTEGER_WEIGHTS, WEIGHT_ONLY, MethodConfig, get_method, registered_methods

PRESET_PATTERNS = {None: "any preset", WEIGHT_ONLY: "W<b>[G<g>]", INTEGER_WEIGHTS: "W<b>[G<g>][A<a>]"}
BASE_FIELDS = {f.name for f in dataclasses.fields(MethodConfig)}


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("methods", help="list the quantization methods cell names can use")
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    parser.set_defaults(func=run)


def describe(method: MethodConfig) -> dict:
    presets = method.presets
    if isinstance(presets, tuple):
        bits, act_bits = presets
        presets = f"W{bits}" + (f"A{act_bits}" if act_bits else "")
    else:
        presets = PRESET_PATTERNS[presets]
    return {
        "method": method.name,
        "cells": f"{method.name}-<preset>-<scope>",
        "presets": presets,
        "statistics": sorted(method.statistics),
        "transforms": list(method.transforms),
        "composes": method.composes,
        "captured": method.uncapturable is None,
        "uncapturable": method.uncapturable,
        "options": {f.name: getattr(method, f.name) for f in dataclasses.fields(method) if f.name not in BASE_FIELDS},
    }


def run(args: argparse.Namespace) -> int:
    rows = [describe(get_method(name)) for name in registered_methods()]
    if args.json:
        print(json.dumps(rows, indent=1))
        return 0
    header = ("method", "presets", "calibration statistics", "transforms first", "captured", "options")
    table = [header] + [(
        row["method"], row["presets"], ", ".join(row["statistics"]) or "none", ", ".join(row["transforms"]) or "-",
        "yes" if row["captured"] else "no", ", ".join(f"{k}={v}" for k, v in row["options"].items()) or "-",
    ) for row in rows]
    widths = [max(len(line[i]) for line in table) for i in range(len(header))]
    for line in table:
        print("  ".join(cell.ljust(width) for cell, width in zip(line, widths, strict=True)).rstrip())
    for row in rows:
        if not row["captured"]:
            print(f"{row['method']}: not captured: {row['uncapturable']}")
    print("cell names: [seed<N>-][steps<N>-]<method>-<preset>-<scope>[-<subset>], e.g. gptq-W4A8-e2e "
          "(grammar: vlaquantbench.cells)")
    return 0
