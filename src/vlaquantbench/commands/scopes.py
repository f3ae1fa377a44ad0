"""`vqb scopes MODEL`: which linear layers a scope and patterns select, counted on the real
architecture built on the meta device (no weights, no memory)."""

from __future__ import annotations

import argparse
import json

from vlaquantbench.errors import UserError
from vlaquantbench.models import get_model_spec, model_names
from vlaquantbench.models.layer_index import write_indexes
from vlaquantbench.quant.subsets import get_subset


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("scopes", help="list the linear layers a scope selects, with counts")
    parser.add_argument("model", nargs="?", help=f"one of {', '.join(model_names())}")
    parser.add_argument("--component", default=None, help="ve, mp, llm, ah, e2e (default) or a join like ve_mp_llm")
    parser.add_argument("--subset", help="a named subset from config/scopes.yaml (sets scope and patterns)")
    parser.add_argument("--only", nargs="+", metavar="PAT", help="keep layers matching any of these globs")
    parser.add_argument("--exclude", nargs="+", metavar="PAT", help="drop layers matching any of these globs")
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    parser.add_argument("--write-index", action="store_true",
                        help="regenerate models/<model>/linears.json (every model when none is given), which the "
                             "workflow checks subset patterns against")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from vlaquantbench.quant.scope import select_layers  # torch: only when it runs

    if args.write_index:
        for path in write_indexes([args.model] if args.model else None):
            print(path)
        return 0
    if args.model is None:
        raise UserError("name a model (or pass --write-index)")
    spec = get_model_spec(args.model)
    scope, only, exclude, expected = args.component or "e2e", args.only, args.exclude, None
    if args.subset:
        if only or exclude:
            raise UserError("--subset already defines the patterns; drop --only/--exclude")
        subset = get_subset(args.model, args.subset)
        if args.component and args.component != subset.scope:
            raise UserError(f"subset {subset.name!r} is defined on scope {subset.scope!r}, not {args.component!r}")
        scope, only, exclude, expected = subset.scope, subset.only, subset.exclude, subset.layers
    selection = select_layers(spec.build("full", device="meta"), spec.components, scope, only, exclude)
    counts = selection.counts()
    total = sum(c["layers"] for c in counts.values())
    out = {
        "model": args.model,
        "scope": scope,
        "only": list(only) if only else None,
        "exclude": list(exclude) if exclude else None,
        "components": counts,
        "layers": list(selection.flat()),
    }
    if expected is not None:
        out["subset"] = {"name": args.subset, "expected_layers": expected, "matches": expected == total}
    if args.json:
        print(json.dumps(out, indent=2))
    else:
        for comp, c in counts.items():
            print(f"{comp:4s} {c['layers']:5d} layers {c['params'] / 1e6:10.1f}M params")
        if expected is not None:
            print(f"subset {args.subset}: {total} layers, paper {expected}")
    return 0 if expected is None or expected == total else 1
