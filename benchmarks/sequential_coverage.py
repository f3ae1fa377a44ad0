"""Confidence sequences at the stop (issue 47): coverage, width and the study level on the authors' records.

1. Coverage under continuous monitoring: from the baseline B of every contrast of tab:clustered and
   tab:lattice, contrasts at a true Delta of 0, -5 and -30 pp (B's recorded per-task rates, A's shifted so
   the task-averaged difference is exactly Delta: the authors' task heterogeneity; baselines below -Delta give
   none), at least `--sequences` per Delta, each its recorded rounds long; covered when Delta lies in the
   confidence sequence at every round.
2. Width: at the fixed design's full sample, the confidence sequence of each of the 40 contrasts against its
   task-clustered bootstrap interval (5,000 draws, per contrast), the ratio of widths averaged over them.
3. Study level: the decisions of each option (e-BH, alpha split) against the per-contrast rule at alpha, listed
   where they differ, with each contrast's tab:clustered bootstrap interval (the table's shared stream).
Minutes on one core: python benchmarks/sequential_coverage.py --out benchmarks/results/sequential_coverage.json
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))

from vlaquantbench.confidence_sequence import contrast_interval  # noqa: E402
from vlaquantbench.records import find_cells, read_cell  # noqa: E402
from vlaquantbench.sequential import Design, paired_rounds, simulate_coverage, study_level  # noqa: E402
from vlaquantbench.stats import task_clustered_bootstrap  # noqa: E402
from vlaquantbench.tables import load_table  # noqa: E402
from vlaquantbench.tables.latex import bootstrapper  # noqa: E402
from vlaquantbench.tables.sequential import sequential_contrasts  # noqa: E402


def clustered_intervals(definition, episodes) -> dict:
    """tab:clustered's printed bootstrap interval of each of its contrasts (its shared stream, in row order)."""
    bootstrap = bootstrapper(definition.bootstrap)
    return {pair: bootstrap(episodes[pair[0]], episodes[pair[1]]) for pair in definition.contrasts()}


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--records", default=str(ROOT.parent / "shared" / "reference" / "records"))
    parser.add_argument("--sequences", type=int, default=10_000, help="simulated contrasts per true Delta, at least")
    parser.add_argument("--deltas", type=float, nargs="+", default=[0.0, -5.0, -30.0])
    parser.add_argument("--alpha", type=float, default=0.05)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args(argv)
    definitions = [load_table(ROOT / "config" / "tables" / f"{name}.yaml") for name in ("clustered", "lattice")]
    contrasts = sequential_contrasts(definitions)
    cells = find_cells(args.records)
    episodes = {ref: read_cell(cells[ref]).episodes for pair in contrasts for ref in pair}
    baselines = [episodes[b] for _, b in contrasts]

    coverage = []
    for delta in args.deltas:
        eligible = sum(frame["success"].mean() >= -delta / 100.0 for frame in baselines)
        started = time.perf_counter()
        result = simulate_coverage(baselines, math.ceil(args.sequences / eligible), delta, args.alpha, args.seed)
        coverage.append({**result, "seconds": round(time.perf_counter() - started, 1)})
        print(json.dumps(coverage[-1]))

    widths = []
    for cell, baseline in contrasts:
        sequence = contrast_interval(paired_rounds(episodes[cell], episodes[baseline]), args.alpha)
        interval = task_clustered_bootstrap(episodes[cell], episodes[baseline])
        widths.append({"cell": cell, "baseline": baseline, "anytime_cs_pp": [round(sequence.low, 2), round(sequence.high, 2)],
                       "bootstrap_pp": [round(interval.low, 2), round(interval.high, 2)],
                       "ratio": round((sequence.high - sequence.low) / (interval.high - interval.low), 3)})
    mean_ratio = float(np.mean([w["ratio"] for w in widths]))
    print(f"width ratio, anytime CS / bootstrap, mean over {len(widths)} contrasts: {mean_ratio:.3f}")

    design = Design(alpha=args.alpha)
    differences = [paired_rounds(episodes[a], episodes[b]) for a, b in contrasts]
    per_contrast, _ = study_level(differences, design, "none")
    clustered = clustered_intervals(definitions[0], episodes)
    study = {}
    for family in ("e_bh", "split"):
        decisions, used = study_level(differences, design, family)
        changed = []
        for (cell, baseline), before, after in zip(contrasts, per_contrast, decisions):
            if before != after:
                interval = clustered.get((cell, baseline))
                changed.append({"cell": cell, "baseline": baseline, "per_contrast": before, "study": after,
                                "clustered_bootstrap_pp": None if interval is None else [interval.low, interval.high],
                                "excludes_zero_by_pp": None if interval is None else max(interval.low, -interval.high, 0.0)})
        study[family] = {"episodes_used": int(sum(used)), "changed": changed,
                         "changed_clustered_beyond_10pp": sum(1 for c in changed if (c["excludes_zero_by_pp"] or 0) > 10)}
        print(f"{family}: {len(changed)} decisions changed, {study[family]['changed_clustered_beyond_10pp']} of them "
              f"tab:clustered contrasts whose interval excludes 0 by more than 10 pp; {sum(used)} episodes")

    result = {"alpha": args.alpha, "contrasts": len(contrasts), "coverage": coverage,
              "width_ratio_mean": round(mean_ratio, 3), "widths": widths, "study_level": study}
    if args.out:
        args.out.write_text(json.dumps(result, indent=2) + "\n")
    return result


if __name__ == "__main__":
    main()
