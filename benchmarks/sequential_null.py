"""Error control of the sequential stopping rule under the authors' task heterogeneity (issue 32).

From every contrast (A, B) of tab:clustered and tab:lattice it builds `--per-pair` null contrasts whose
true difference is zero (each task's outcomes of A and B pooled and relabelled at random, in a random
episode order) and as many at the margin boundary (B's episodes drawn from its recorded per-task rates,
A's from those rates shifted down so the task-averaged difference is exactly -margin), runs the stopping
rule on each and reports the false-decision rates (`worse` for the first, `not_worse` for the second).
Seconds on one core: python benchmarks/sequential_null.py --out benchmarks/results/sequential_null.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))

from vlaquantbench.records import find_cells, read_cell  # noqa: E402
from vlaquantbench.sequential import Design, simulate_false_decisions  # noqa: E402
from vlaquantbench.tables import load_table  # noqa: E402
from vlaquantbench.tables.sequential import sequential_contrasts  # noqa: E402


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--records", default=str(ROOT.parent / "shared" / "reference" / "records"))
    parser.add_argument("--tables", nargs="+", default=["clustered", "lattice"])
    parser.add_argument("--per-pair", type=int, default=250, help="null contrasts of each kind per recorded contrast")
    parser.add_argument("--alpha", type=float, default=0.05)
    parser.add_argument("--margin", type=float, default=5.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args(argv)
    contrasts = sequential_contrasts([load_table(ROOT / "config" / "tables" / f"{name}.yaml") for name in args.tables])
    cells = find_cells(args.records)
    episodes = {ref: read_cell(cells[ref]).episodes for pair in contrasts for ref in pair}
    result = simulate_false_decisions([(episodes[a], episodes[b]) for a, b in contrasts], args.per_pair,
                                      Design(alpha=args.alpha, margin_pp=args.margin), seed=args.seed)
    result["tables"] = args.tables
    text = json.dumps(result, indent=2)
    print(text)
    if args.out:
        args.out.write_text(text + "\n")
    return result


if __name__ == "__main__":
    main()
