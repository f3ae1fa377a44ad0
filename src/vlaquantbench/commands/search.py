"""`vqb search RECORDS_DIR --csv FILE`: the cheapest recorded cell decided not worse than full precision.

The candidates are the cells of the baseline's benchmark, suite and model in the folder (`--cells` narrows them
by name patterns); each is an allocation (its scope and subset at its preset, the rest at full precision) costed
by its weight memory on the model's committed layer index. `vlaquantbench.search` visits them cheapest first
(equal costs: the lower sum of the per-component layer errors its header reports), runs the stopping rule on
each one's recorded rounds against the baseline at alpha / K, prunes after `worse` and stops at the first
`not_worse`. The CSV has one row per candidate in search order (status, decision, episodes read, A - B and the
success rate at the stop with confidence sequences, Pareto front) after the baseline's row; `--exhaustive` also
decides every candidate and reports whether the search chose what deciding them all would have.
"""

from __future__ import annotations

import argparse
import fnmatch
import sys

from vlaquantbench.errors import UserError

DEFAULT_BASELINE = "rtn-BASELINE-e2e"


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("search", help="closed-loop precision search over a folder of cell records")
    parser.add_argument("records_dir", help="folder of cell folders (episodes.parquet and header.json)")
    parser.add_argument("--baseline", default=DEFAULT_BASELINE, metavar="CELL",
                        help=f"the full-precision cell: its name (default {DEFAULT_BASELINE}), one such cell in the "
                             "folder, or its reference (e.g. libero/libero_spatial/pi05/rtn-BASELINE-e2e)")
    parser.add_argument("--cells", nargs="+", metavar="PATTERN",
                        help="the candidates: cell names matching any of these patterns (default: every other cell "
                             "of the baseline's model and suite)")
    parser.add_argument("--alpha", type=float, default=0.05,
                        help="level of the whole search, split over the candidates (default 0.05)")
    parser.add_argument("--margin", type=float, default=5.0, metavar="PP",
                        help="`not_worse`: not worse than the baseline by more than this many pp (default 5)")
    parser.add_argument("--exhaustive", action="store_true",
                        help="also decide every candidate and say whether the search chose the same")
    parser.add_argument("--csv", required=True, metavar="FILE", help="CSV to write, one row per candidate")
    parser.set_defaults(func=run)


def _proxy(header: dict) -> float | None:
    """The sum over components of the header's mean relative output error (None where it reports none)."""
    errors = [v["mean_rel_mse"] for v in (header.get("quant_report") or {}).values()
              if isinstance(v, dict) and v.get("mean_rel_mse") is not None]
    return sum(errors) if errors else None


def run(args: argparse.Namespace) -> int:
    import pandas as pd

    from vlaquantbench.records import contrast_mismatch, find_cells, read_cell
    from vlaquantbench.search import (Candidate, SearchDesign, exhaustive, pareto_front, precision_search,
                                      records_decider)
    from vlaquantbench.atomic import write_text

    design = SearchDesign(args.alpha, args.margin)
    design.per_candidate(1)  # a bad level or margin is refused before any record is read
    cells = find_cells(args.records_dir)
    baselines = [ref for ref in cells if args.baseline in (ref, ref.rsplit("/", 1)[-1])]
    if len(baselines) != 1:
        raise UserError(f"--baseline {args.baseline!r}: {len(baselines)} such cells in {args.records_dir} "
                        f"({', '.join(baselines) or 'none'}); the search needs exactly one")
    baseline = baselines[0]
    group = baseline.rsplit("/", 1)[0]
    names = {ref: ref.rsplit("/", 1)[-1] for ref in cells if ref.rsplit("/", 1)[0] == group and ref != baseline}
    if args.cells:
        names = {ref: name for ref, name in names.items() if any(fnmatch.fnmatchcase(name, p) for p in args.cells)}
    if not names:
        raise UserError(f"no candidate cell of {group} in {args.records_dir}"
                        + (f" matches --cells {' '.join(args.cells)}" if args.cells else ""))
    records = {ref: read_cell(cells[ref]) for ref in [baseline, *names]}
    for ref in names:
        mismatch = contrast_mismatch(records[ref], records[baseline])
        if mismatch:
            raise UserError(f"cell {ref} cannot be contrasted with {baseline}: {mismatch}")
    candidates = [Candidate.from_ref(ref, _proxy(records[ref].header)) for ref in names]
    decide = records_decider({ref: c.episodes for ref, c in records.items()},
                             {ref: c.header for ref, c in records.items()}, baseline)
    result = precision_search(candidates, decide, design)
    rows = result.rows()
    rows.insert(0, {"order": 0, "cell": baseline, "cost_ratio": 1.0, "status": "baseline (runs in full)",
                    "episodes_used": len(records[baseline].episodes),
                    "rate_at_stop": 100.0 * records[baseline].episodes["success"].mean()})
    front = pareto_front(rows)
    table = pd.DataFrame(rows).assign(pareto=lambda t: t["cell"].isin(front))
    summary = [f"{design.guarantee(len(candidates))}.",
               f"chosen: {result.chosen.ref if result.chosen else 'none (no candidate decided not_worse)'}"
               + (f" at {result.chosen.cost_ratio:.3f} x the BF16 weight memory" if result.chosen else ""),
               f"episodes: {result.episodes_spent} of {result.episodes_exhaustive} that every candidate run in full "
               f"would need ({len(result.verdicts)} visited, {len(result.pruned_by)} pruned)"]
    if args.exhaustive:
        chosen, _ = exhaustive(candidates, decide, design)
        same = (chosen.ref if chosen else None) == (result.chosen.ref if result.chosen else None)
        summary.append(f"exhaustive: {chosen.ref if chosen else 'none'} ({'the same' if same else 'NOT the same'})")
    write_text(args.csv, table.to_csv(index=False, float_format="%.4f"))
    print("\n".join(summary))
    return 0
