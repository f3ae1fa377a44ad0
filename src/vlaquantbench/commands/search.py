"""`vqb search RECORDS_DIR --csv FILE`: the cheapest recorded cell decided not worse than full precision.

The candidates are the cells of the baseline's benchmark, suite and model in the folder (`--cells` narrows them
by name patterns); each is an allocation (its scope and subset at its preset, the rest at full precision) costed
by its weight memory on the model's committed layer index (cells of another run seed, `seed<N>-`, are left out). `vlaquantbench.search` visits them cheapest first
(equal costs: the lower sum of the per-component layer errors its header reports), runs the stopping rule on
each one's recorded rounds against the baseline at alpha / K, prunes after `worse` and stops at the first
`not_worse`. The CSV has one row per candidate in search order (status, decision, episodes read, A - B and the
success rate at the stop with confidence sequences, Pareto front) after the baseline's row; `--exhaustive` also
decides every candidate and reports whether the search chose what deciding them all would have; `--confirm-seed N`
contrasts the chosen cell with the baseline on run seed N's records (`seed<N>-<cell>`, in `--confirm-dir`);
`--chosen FILE` writes the chosen allocation by name (`study.allocations.<--allocation>`, a config to add after the
study's, so that a cell `alloc-<name>` is the chosen cell).

`--space TABLE` (a table definition YAML, e.g. config/gpu_search/tables/gpu_search.yaml) names the whole space:
its cells of the baseline's benchmark, suite and model, recorded in the folder or not. A folder holding only a part
of it (a run cut short) is searched over the whole space (alpha split over all of it): the answer when the
recorded candidates determine it (the cheaper ones decided or at their cap, and a `not_worse` among them), else a
refusal naming the candidates without records that the search would read.
"""

from __future__ import annotations

import argparse
import fnmatch
import re

from vlaquantbench.errors import UserError

DEFAULT_BASELINE = "rtn-BASELINE-e2e"
DEFAULT_ALLOCATION = "search"  # vlaquantbench.tables.search's (not imported here: registering the parser imports no pandas)


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("search", help="closed-loop precision search over a folder of cell records")
    parser.add_argument("records_dir", help="folder of cell records (authors' .jsonl or cell folders)")
    parser.add_argument("--baseline", default=DEFAULT_BASELINE, metavar="CELL",
                        help=f"the full-precision cell: its name (default {DEFAULT_BASELINE}), one such cell in the "
                             "folder, or its reference (<benchmark>/<suite>/<model>/<cell>)")
    parser.add_argument("--cells", nargs="+", metavar="PATTERN",
                        help="the candidates: cell names matching any of these patterns (default: every other cell "
                             "of the baseline's model and suite)")
    parser.add_argument("--space", metavar="TABLE",
                        help="the whole search space: a table definition YAML whose cells of the baseline's model and "
                             "suite are the candidates, recorded in RECORDS_DIR or not (a run cut short)")
    parser.add_argument("--alpha", type=float, default=0.05,
                        help="level of the whole search, split over the candidates (default 0.05)")
    parser.add_argument("--margin", type=float, default=5.0, metavar="PP",
                        help="`not_worse`: not worse than the baseline by more than this many pp (default 5)")
    parser.add_argument("--exhaustive", action="store_true",
                        help="also decide every candidate and say whether the search chose the same")
    parser.add_argument("--csv", required=True, metavar="FILE", help="CSV to write, one row per candidate")
    parser.add_argument("--confirm-seed", type=int, metavar="N",
                        help="confirm the chosen cell against the baseline on run seed N's episodes (cells "
                             "seed<N>-<cell>, run in full), never used by the search")
    parser.add_argument("--confirm-dir", metavar="DIR", help="where those records are (default RECORDS_DIR)")
    parser.add_argument("--figure", metavar="PDF", help="also plot success against weight memory (the Pareto front)")
    parser.add_argument("--chosen", metavar="YAML",
                        help="also write the chosen allocation by name: a config setting study.allocations.NAME to the "
                             "chosen cell's name, so that a cell alloc-NAME is that cell")
    parser.add_argument("--allocation", default=DEFAULT_ALLOCATION, metavar="NAME",
                        help=f"the name --chosen registers (default {DEFAULT_ALLOCATION}; lower case, digits, _)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from vlaquantbench.records import find_cells, read_cell
    from vlaquantbench.search import SearchDesign
    from vlaquantbench.tables.search import write_search

    design = SearchDesign(args.alpha, args.margin)
    design.per_candidate(1)  # a bad level or margin is refused before any record is read
    cells = find_cells(args.records_dir)
    baselines = [ref for ref in cells if args.baseline in (ref, ref.rsplit("/", 1)[-1])]
    if len(baselines) != 1:
        raise UserError(f"--baseline {args.baseline!r}: {len(baselines)} such cells in {args.records_dir} "
                        f"({', '.join(baselines) or 'none'}); the search needs exactly one")
    baseline = baselines[0]
    group = baseline.rsplit("/", 1)[0]
    # Cells of another run seed (`seed<N>-`) run other episodes: a confirmation's, never a candidate.
    names = [ref for ref in cells if ref.rsplit("/", 1)[0] == group and ref != baseline
             and not re.match(r"seed\d+-", ref.rsplit("/", 1)[-1])]
    space = None
    if args.space:
        from vlaquantbench.tables import load_table

        space = [ref for ref in dict.fromkeys(load_table(args.space).refs())
                 if ref.rsplit("/", 1)[0] == group and ref != baseline]
        if not space:
            raise UserError(f"--space {args.space}: the table holds no cell of {group} but its baseline")
        names = [ref for ref in names if ref in space]
    if args.cells:
        names = [ref for ref in names if any(fnmatch.fnmatchcase(ref.rsplit("/", 1)[-1], p) for p in args.cells)]
    if args.cells and space is not None:
        space = [ref for ref in space if any(fnmatch.fnmatchcase(ref.rsplit("/", 1)[-1], p) for p in args.cells)]
    if not (space or names):
        raise UserError(f"no candidate cell of {group} in {args.space or args.records_dir}"
                        + (f" matches --cells {' '.join(args.cells)}" if args.cells else ""))
    held = {}
    if args.confirm_seed is not None:
        found = find_cells(args.confirm_dir or args.records_dir)
        prefix = f"seed{args.confirm_seed}-"
        held = {ref: read_cell(path) for ref, path in found.items() if ref.rsplit("/", 1)[-1].startswith(prefix)}
    report = write_search({ref: read_cell(cells[ref]) for ref in [baseline, *names]}, baseline, design, args.csv,
                          args.figure, args.exhaustive, held, args.confirm_seed, args.chosen, args.allocation,
                          [baseline, *space] if space is not None else None)
    print("\n".join(report.summary()))
    return 0
