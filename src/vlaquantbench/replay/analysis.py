"""Replay outputs of one format -> `analysis.json` in the authors' layout.

The layout (keys `records`, `configs`, `additivity`, `recovery`, `repeatability_floor`,
`fp_mean_abs_action`) is what the replay tables read, so they render the authors' files and
this project's alike.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vlaquantbench.atomic import write_text
from vlaquantbench.errors import UserError
from vlaquantbench.replay import composition as C
from vlaquantbench.replay.run import ReplayRun

ADDITIVITY_DEFINITION = (
    "e_c = chunk_c - chunk_baseline on identical observations and identical flow noise; "
    "sum = e_{a} + e_{b}; residual = ||e_{union} - sum|| / ||e_{union}||"
)


@dataclass(frozen=True)
class Roles:
    """Which replayed configurations play which part in the composition and recovery tests."""

    baseline: str = "baseline"
    repeat: str | None = "baseline2"  # second full-precision replay: the repeatability floor
    a: str = "attention"
    b: str = "adarms"
    union: str = "union"
    smaller: str = "s126"
    larger: str = "s167"

    @classmethod
    def from_study(cls, study: dict) -> "Roles":
        return cls(baseline=study["baseline"], repeat=study.get("repeat"), **study["composition"], **study["recovery"])


def config_summary(run: ReplayRun, baseline: ReplayRun) -> dict:
    """One configuration's entry under `configs`, errors measured against the full-precision replay."""
    actions, ref_actions = run.stacked("actions"), baseline.stacked("actions")
    per_chunk = C.chunk_mae(run.stacked("chunks"), baseline.stacked("chunks"))
    down = C.average_call_stats([run.arrays[r]["downproj"] for r in run.record_names()])
    col = {name: down[i] for i, name in enumerate(C.DOWNPROJ_COLUMNS)}
    return {
        "preset": run.summary["preset"],
        "quantized_layers": run.summary["quantized_layers"],
        **C.executed_action_errors(actions, ref_actions),
        "chunk_mae_mean": float(per_chunk.mean()),
        "chunk_mae_median": float(np.median(per_chunk)),
        "flow_step_divergence": C.flow_state_deviation(run.stacked("flow_states"), baseline.stacked("flow_states")),
        "downproj_tok_absmax_mean": float(col["tok_absmax_mean"]),
        "downproj_tok_absmax_p99": float(col["tok_absmax_p99"]),
        "downproj_abs_kurtosis": float(col["abs_kurtosis"]),
        # Unweighted over trajectories, as the authors' files report it.
        "dev_from_recorded_actions": float(np.mean([r["dev_from_recorded_actions"] for r in run.summary["records"]])),
    }


def additivity(runs: dict[str, ReplayRun], roles: Roles) -> dict:
    ref = runs[roles.baseline].stacked("chunks")
    e = {k: C.error_vectors(runs[k].stacked("chunks"), ref) for k in (roles.a, roles.b, roles.union)}
    args = (e[roles.union], e[roles.a], e[roles.b])
    return {
        "n_chunks": int(len(ref)),
        "norm_union_over_sum_of_norms": C.median_iqr(C.norm_ratio(*args)),
        "norm_union_over_norm_of_sum": {"median": float(np.median(C.norm_ratio_to_sum(*args)))},
        "residual_over_union": C.median_iqr(C.residual(*args)),
        "cosine_union_vs_sum": C.median_iqr(C.cosine(*args)),
        "definition": ADDITIVITY_DEFINITION.format(a=roles.a, b=roles.b, union=roles.union),
    }


def recovery(runs: dict[str, ReplayRun], roles: Roles) -> dict:
    ref = runs[roles.baseline].stacked("chunks")
    small, large = runs[roles.smaller], runs[roles.larger]
    mae_small, mae_large = C.chunk_mae(small.stacked("chunks"), ref), C.chunk_mae(large.stacked("chunks"), ref)
    n_small, n_large = small.summary["quantized_layers"], large.summary["quantized_layers"]
    return {
        f"chunk_mae_{n_small}": float(mae_small.mean()),
        f"chunk_mae_{n_large}": float(mae_large.mean()),
        f"frac_chunks_{n_large}_lower": C.share_lower(mae_large, mae_small),
        "n_chunks": int(len(ref)),
    }


def analyze(runs: list[ReplayRun], roles: Roles = Roles()) -> dict:
    """All statistics of one format's replays (the baseline replay is the reference)."""
    by_name = {r.name: r for r in runs}
    needed = [roles.baseline, roles.a, roles.b, roles.union, roles.smaller, roles.larger]
    missing = [n for n in needed if n not in by_name]
    if missing:
        raise UserError(f"replay analysis needs configurations {missing}; got {sorted(by_name)}")
    baseline = by_name[roles.baseline]
    for run in runs:
        if run.record_names() != baseline.record_names():
            raise UserError(f"replay {run.name!r} covers other trajectories than {baseline.name!r}")
    floor = 0.0
    if roles.repeat in by_name:
        floor = float(np.abs(by_name[roles.repeat].stacked("actions") - baseline.stacked("actions")).max())
    return {
        "records": baseline.summary["records"],
        "configs": {name: config_summary(by_name[name], baseline) for name in sorted(by_name)},
        "additivity": additivity(by_name, roles),
        "recovery": recovery(by_name, roles),
        "repeatability_floor": floor,
        "fp_mean_abs_action": float(np.abs(baseline.stacked("actions")).mean()),
        "created": time.strftime("%Y-%m-%dT%H:%M:%S"),
    }


def analyze_files(summaries: list[str | Path], output: str | Path, study: dict | None = None,
                  arrays: list[str | Path] | None = None) -> dict:
    """Snakemake entry: replay summaries and their arrays files (default: beside them) -> analysis.json."""
    roles = Roles.from_study(study) if study else Roles()
    arrays = arrays or [None] * len(summaries)
    if len(arrays) != len(summaries):
        raise UserError(f"{len(summaries)} replay summaries but {len(arrays)} arrays files")
    result = analyze([ReplayRun.load(p, a) for p, a in zip(summaries, arrays)], roles)
    write_text(output, json.dumps(result, indent=1))
    return result
