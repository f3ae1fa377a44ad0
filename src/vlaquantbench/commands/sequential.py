"""`vqb sequential RECORDS_DIR [--baseline CELL] --csv FILE`: replay the stopping rule on recorded cells.

Every cell of the folder is contrasted with the baseline of its model, benchmark and suite (by default each
`<benchmark>/<suite>/<model>/rtn-BASELINE-e2e`): its episodes, in the task-interleaved order, go through the
anytime-valid stopping rule (`vlaquantbench.sequential`), and the CSV gives per contrast the episodes used,
the decision, A - B and A's rate at the stop with their confidence sequences, the study's decision under
`--family` (over the contrasts left), and, for cells whose records ran in full, the full-sample clustered
bootstrap and its decision. A cell that has no such baseline, or whose tasks or episode seeds are not its
baseline's (`records.contrast_mismatch`), is skipped, named on stderr with the reason, before any contrast
is computed.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from vlaquantbench.errors import UserError

DEFAULT_BASELINE = "rtn-BASELINE-e2e"


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("sequential", help="replay the sequential stopping rule on a folder of cell records")
    parser.add_argument("records_dir", help="folder of cell records (authors' .jsonl or cell folders)")
    parser.add_argument("--baseline", default=DEFAULT_BASELINE, metavar="CELL",
                        help="a cell name: each model's and suite's cell of that name is the baseline of the others of "
                             f"its model and suite (default {DEFAULT_BASELINE}); or one cell, by its reference under "
                             "RECORDS_DIR (<benchmark>/<suite>/<model>/<cell>) or its file: the baseline "
                             "of the cells of its model and suite only")
    parser.add_argument("--alpha", type=float, default=0.05, help="declared level of the rule (default 0.05)")
    parser.add_argument("--margin", type=float, default=5.0, metavar="PP",
                        help="`not_worse` means not worse than the baseline by more than this many pp (default 5)")
    parser.add_argument("--family", metavar="OPTION",
                        help="study-level guarantee over the contrasts: e_bh, e-BH on the capitals (a false-discovery "
                             "rate, the default); split, alpha split over them (a family-wise error rate); or none")
    parser.add_argument("--csv", required=True, metavar="FILE", help="CSV to write, one row per contrast")
    parser.set_defaults(func=run)


def _group(ref: str) -> str:
    """`<benchmark>/<suite>/<model>` of a cell reference: the cells one baseline serves."""
    return ref.rsplit("/", 1)[0]


def _baselines(baseline: str, cells: dict, records_dir: str) -> tuple[dict[str, str], str]:
    """The baseline of each `<benchmark>/<suite>/<model>` that has one: the cell `baseline` names (a reference
    or a record path: that cell's group alone), or each group's cell of that name; and why a group has none."""
    given = Path(baseline).resolve()
    one = [ref for ref, path in cells.items() if ref == baseline or Path(path).resolve() in {given, given / "episodes.parquet"}]
    if one:
        return {_group(one[0]): one[0]}, f"the baseline {one[0]} is of another model or suite"
    named = [ref for ref in cells if ref.rsplit("/", 1)[-1] == baseline]
    if not named:
        raise UserError(f"--baseline {baseline!r} is no cell there (cells in {records_dir}: {', '.join(cells)})")
    return {_group(ref): ref for ref in named}, f"its model and suite have no cell {baseline} in {records_dir}"


def run(args: argparse.Namespace) -> int:
    # pandas and the records: only when it runs
    from vlaquantbench.records import contrast_mismatch, find_cells, read_cell
    from vlaquantbench.sequential import (DEFAULT_FAMILY, Design, ran_in_full, retrospective,
                                          saved_fraction, study_design, write_csv)

    design = Design(alpha=args.alpha, margin_pp=args.margin)  # refuses a bad level before any record is read
    family = args.family or DEFAULT_FAMILY
    study_design(design, family, 1)  # and a bad study-level option
    cells = find_cells(args.records_dir)
    baselines, without_baseline = _baselines(args.baseline, cells, args.records_dir)
    records = {ref: read_cell(path) for ref, path in cells.items()}
    contrasts, skipped = [], []
    for ref in cells:
        baseline = baselines.get(_group(ref))
        if ref == baseline:
            continue
        if baseline is None:
            skipped.append((ref, without_baseline))
            continue
        mismatch = contrast_mismatch(records[ref], records[baseline])
        if mismatch:
            skipped.append((ref, f"not comparable with {baseline}: {mismatch}"))
        else:
            contrasts.append((ref, baseline))
    for ref, reason in skipped:
        print(f"skipped {ref}: {reason}", file=sys.stderr)
    if not contrasts:
        raise UserError(f"{args.records_dir} holds no cell to contrast with {', '.join(sorted(baselines.values()))}"
                        + (f" ({len(skipped)} skipped, above)" if skipped else ""))
    table = retrospective(contrasts, {ref: cell.episodes for ref, cell in records.items()}, design, family,
                          stopped_early={ref for ref, cell in records.items() if not ran_in_full(cell.header)})
    print(write_csv(table, args.csv))
    print(f"{len(table)} contrasts with {len({b for _, b in contrasts})} baseline(s), "
          f"{len(skipped)} cell(s) skipped: {int(table['episodes_used'].sum())} of "
          f"{int(table['episodes_available'].sum())} episodes ({100 * saved_fraction(table):.1f}% fewer); "
          + ", ".join(f"{(table['decision'] == d).sum()} {d}" for d in ("worse", "not_worse", "undecided"))
          + f"; {int((~table['agrees']).sum())} contradicting the full-sample decision; "
          + f"{int((table['study_decision'] != table['decision']).sum())} changed by the study level ({family})")
    return 0
