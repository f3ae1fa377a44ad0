"""`vqb sequential RECORDS_DIR --baseline CELL --csv FILE`: replay the stopping rule on recorded cells.

Every cell of the folder other than the baseline is contrasted with it: its episodes, in the
task-interleaved order, go through the anytime-valid stopping rule (`vlaquantbench.sequential`), and the
CSV gives per contrast the episodes used, the decision, A - B and A's rate at the stop with their confidence
sequences, the study's decision under `--family`, and, for cells whose records ran in full, the full-sample
clustered bootstrap and its decision.
"""

from __future__ import annotations

import argparse

from vlaquantbench.errors import UserError


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("sequential", help="replay the sequential stopping rule on a folder of cell records")
    parser.add_argument("records_dir", help="folder of cell records (authors' .jsonl or cell folders)")
    parser.add_argument("--baseline", required=True, metavar="CELL",
                        help="the baseline cell: its reference under RECORDS_DIR (e.g. libero/libero_spatial/pi05/"
                             "rtn-BASELINE-e2e), its file, or its name when that is unique in the folder")
    parser.add_argument("--alpha", type=float, default=0.05, help="declared level of the rule (default 0.05)")
    parser.add_argument("--margin", type=float, default=5.0, metavar="PP",
                        help="`not_worse` means not worse than the baseline by more than this many pp (default 5)")
    parser.add_argument("--family", metavar="OPTION",
                        help="study-level guarantee over the contrasts: e_bh, e-BH on the capitals (a false-discovery "
                             "rate, the default); split, alpha split over them (a family-wise error rate); or none")
    parser.add_argument("--csv", required=True, metavar="FILE", help="CSV to write, one row per contrast")
    parser.set_defaults(func=run)


def _baseline_ref(baseline: str, cells: dict, records_dir: str) -> str:
    """The reference of `baseline` given as a reference, a record path or a unique cell name."""
    from pathlib import Path

    if baseline in cells:
        return baseline
    by_path = [ref for ref, path in cells.items() if Path(path).resolve() in {Path(baseline).resolve(),
                                                                                 (Path(baseline) / "episodes.parquet").resolve()}]
    by_name = [ref for ref in cells if ref.rsplit("/", 1)[-1] == baseline]
    found = by_path or by_name
    if len(found) != 1:
        where = "matches several cells: " + ", ".join(found) if found else "is no cell there"
        raise UserError(f"--baseline {baseline!r} {where} (cells in {records_dir}: {', '.join(cells)})")
    return found[0]


def run(args: argparse.Namespace) -> int:
    # pandas and the records: only when it runs
    from vlaquantbench.records import find_cells, read_cell
    from vlaquantbench.sequential import DEFAULT_FAMILY, Design, ran_in_full, retrospective, saved_fraction, study_design, write_csv

    design = Design(alpha=args.alpha, margin_pp=args.margin)  # refuses a bad level before any record is read
    family = args.family or DEFAULT_FAMILY
    study_design(design, family, 1)  # and a bad study-level option
    cells = find_cells(args.records_dir)
    baseline = _baseline_ref(args.baseline, cells, args.records_dir)
    others = [ref for ref in cells if ref != baseline]
    if not others:
        raise UserError(f"{args.records_dir} holds no cell besides the baseline {baseline}")
    records = {ref: read_cell(path) for ref, path in cells.items()}
    table = retrospective([(ref, baseline) for ref in others], {ref: cell.episodes for ref, cell in records.items()},
                          design, family, stopped_early={ref for ref, cell in records.items() if not ran_in_full(cell.header)})
    print(write_csv(table, args.csv))
    print(f"{len(table)} contrasts with {baseline}: {int(table['episodes_used'].sum())} of "
          f"{int(table['episodes_available'].sum())} episodes ({100 * saved_fraction(table):.1f}% fewer); "
          + ", ".join(f"{(table['decision'] == d).sum()} {d}" for d in ("worse", "not_worse", "undecided"))
          + f"; {int((~table['agrees']).sum())} contradicting the full-sample decision; "
          + f"{int((table['study_decision'] != table['decision']).sum())} changed by the study level ({family})")
    return 0
