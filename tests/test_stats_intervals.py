"""Statistics: Wilson intervals against the authors' summary, the task-clustered bootstrap, Spearman."""

import csv

import numpy as np
import pandas as pd
import pytest
from scipy.stats import rankdata

from vlaquantbench.errors import UserError
from vlaquantbench.records import read_cell
from vlaquantbench.stats import spearman, task_clustered_bootstrap, wilson_interval
from paths import REFERENCE

SPATIAL = REFERENCE / "records" / "libero" / "libero_spatial"


def cell(outcomes_per_task):
    rows = [
        {"task_id": task, "episode": ep, "seed": ep, "success": bool(ok)}
        for task, outcomes in enumerate(outcomes_per_task)
        for ep, ok in enumerate(outcomes)
    ]
    return pd.DataFrame(rows)


def test_wilson_matches_every_row_of_the_authors_summary():
    rows = list(csv.DictReader(open(REFERENCE / "authors-summary.csv", newline="")))
    assert len(rows) == 417
    low, high = wilson_interval([int(r["successes"]) for r in rows], [int(r["episodes"]) for r in rows])
    assert np.round(low, 2).tolist() == [float(r["ci_low"]) for r in rows]
    assert np.round(high, 2).tolist() == [float(r["ci_high"]) for r in rows]


def test_wilson_is_the_appendix_formula():
    k, n, z = 187, 200, 1.96
    p = k / n
    centre, half = p + z**2 / (2 * n), z * np.sqrt(p * (1 - p) / n + z**2 / (4 * n**2))
    low, high = wilson_interval(k, n)
    assert low == pytest.approx(100 * (centre - half) / (1 + z**2 / n), abs=1e-9)
    assert high == pytest.approx(100 * (centre + half) / (1 + z**2 / n), abs=1e-9)


def test_bootstrap_is_reproducible_and_seeded():
    a = read_cell(SPATIAL / "pi05" / "rtn-W4A4-ah.jsonl").episodes
    b = read_cell(SPATIAL / "pi05" / "ablate-W4A4-ah-down_attn_adarms.jsonl").episodes
    first, again = task_clustered_bootstrap(a, b), task_clustered_bootstrap(a, b)
    assert first == again and first.delta == pytest.approx(63.5)
    assert first.low < first.delta < first.high
    assert task_clustered_bootstrap(a, b, seed=1) != first


def test_bootstrap_degenerate_contrasts():
    ones, zeros = cell([[1] * 20] * 10), cell([[0] * 20] * 10)
    full = task_clustered_bootstrap(ones, zeros)
    assert (full.delta, full.low, full.high) == (100.0, 100.0, 100.0)
    same = read_cell(SPATIAL / "pi05" / "rtn-BASELINE-e2e.jsonl").episodes
    assert task_clustered_bootstrap(same, same).delta == 0.0


def test_bootstrap_clusters_by_task():
    # Task-level heterogeneity widens the interval: tasks all-or-nothing vs. the same rate spread evenly.
    clustered = cell([[1] * 20] * 5 + [[0] * 20] * 5)
    spread = cell([[1] * 10 + [0] * 10] * 10)
    reference = cell([[0] * 20] * 10)
    wide, narrow = task_clustered_bootstrap(clustered, reference), task_clustered_bootstrap(spread, reference)
    assert wide.delta == narrow.delta == 50.0
    assert (wide.high - wide.low) > 2 * (narrow.high - narrow.low)
    # a task with fewer episodes only resamples its own episodes
    ragged = cell([[1] * 20] * 9 + [[1] * 19])
    assert task_clustered_bootstrap(ragged, reference).low == 100.0


def literal_bootstrap(a, b, draws, rng):
    """The paper's procedure call by call: per draw T task picks, then per picked task A's and B's episodes."""
    tasks = sorted(a["task_id"].unique())
    groups = [[cell.loc[cell["task_id"] == t, "success"].to_numpy(float) for t in tasks] for cell in (a, b)]
    differences = []
    for _ in range(draws):
        values = []
        for pick in rng.integers(0, len(tasks), len(tasks)):
            x, y = groups[0][pick], groups[1][pick]
            x, y = x[rng.integers(0, len(x), len(x))], y[rng.integers(0, len(y), len(y))]
            values.append(x.mean() - y.mean())
        differences.append(100 * np.mean(values))
    return np.percentile(differences, [2.5, 97.5])


@pytest.mark.parametrize("ragged", [False, True])
def test_bootstrap_consumes_the_stream_as_the_literal_procedure(ragged):
    """Batched draws equal the call-by-call procedure on a continued stream, for equal and unequal task sizes."""
    a = read_cell(SPATIAL / "pi05" / "ablate-W4A4-ah-onlyadarms.jsonl").episodes
    b = read_cell(SPATIAL / "xvla" / "rtn-BASELINE-e2e.jsonl").episodes  # 19 episodes per task
    if ragged:
        a = a[~((a["task_id"] == 3) & (a["episode"] >= 15))]  # task 3 keeps 15 episodes
    ours, theirs = np.random.default_rng(7), np.random.default_rng(7)
    for _ in range(2):  # the second contrast continues both streams
        got = task_clustered_bootstrap(a, b, draws=300, rng=ours)
        assert [got.low, got.high] == literal_bootstrap(a, b, 300, theirs).tolist()
    assert ours.integers(0, 2**62) == theirs.integers(0, 2**62)  # both streams at the same position


def test_bootstrap_needs_the_same_tasks():
    with pytest.raises(UserError, match="same tasks"):
        task_clustered_bootstrap(cell([[1]] * 10), cell([[1]] * 9))


def test_spearman_uses_average_ranks_for_ties():
    x, y = [0.3, 0.1, 0.1, 0.7, 0.5], [2.0, 1.0, 3.0, 5.0, 4.0]
    expected = np.corrcoef(rankdata(x), rankdata(y))[0, 1]  # Pearson on average ranks
    assert spearman(x, y) == pytest.approx(expected)
    assert spearman([1, 2, 3], [3, 2, 1]) == pytest.approx(-1.0)
