"""Issue 47: confidence sequences at the stopping rule's stop, paired contrasts, and the study-level option.

The independent check is capitals computed by hand on a small example (confseq, the reference implementation,
neither builds nor imports here: see `vlaquantbench.sequential`); coverage is simulated under the authors' task
heterogeneity (the full run: benchmarks/sequential_coverage.py); the live table, summary.csv and `vqb sequential`
are read from the committed trained-policy records."""

import csv
import json

import numpy as np
import pandas as pd
import pytest

from paths import RECORDS, ROOT
from vlaquantbench.cli import main
from vlaquantbench.confidence_sequence import (HEDGE, TRUNCATION, _log_capital_above, _lower_ends, contrast_interval,
                                               mean_sequence, plug_in_bets, rate_interval)
from vlaquantbench.records import find_cells, read_cell
from vlaquantbench.sequential import (Design, e_bh, outcome_rounds, paired_rounds, retrospective, simulate_coverage,
                                      study_level)
from vlaquantbench.stats import task_clustered_bootstrap
from vlaquantbench.tables import load_table
from vlaquantbench.tables.latex import bootstrapper, read_cells, render_latex
from vlaquantbench.tables.sequential import sequential_contrasts
from vlaquantbench.tables.summary import summarize

LIVE = ROOT / "results/trained_sequential/live"
BASE = "metaworld/metaworld_mt50/pi05/"
BASELINE, STOPPED, CAPPED = BASE + "rtn-BASELINE-e2e", BASE + "rtn-W2A2-e2e", BASE + "rtn-W4A8-e2e"


@pytest.fixture(scope="module")
def paper():
    """The 40 contrasts of tab:clustered and tab:lattice, their episodes and tab:clustered's definition."""
    definitions = [load_table(ROOT / "config" / "tables" / f"{name}.yaml") for name in ("clustered", "lattice")]
    contrasts = sequential_contrasts(definitions)
    cells = find_cells(RECORDS)
    return contrasts, {ref: read_cell(cells[ref]).episodes for pair in contrasts for ref in pair}, definitions[0]


def test_bets_and_capital_match_a_hand_computation():
    # One task, outcomes 1, 0, 1. Before round 1: variance 1/4, t = 1: sqrt(1 / (0.25 ln 2)) = 2.40224.
    # After x1 = 1: mean (0.5 + 1) / 2 = 0.75, variance (0.25 + 0.25^2) / 2 = 0.15625; t = 2: sqrt(1 / (0.3125 ln 3)).
    # After x2 = 0: mean 1.5 / 3 = 0.5, variance (0.3125 + 0.25) / 3 = 0.1875; t = 3: sqrt(1 / (0.5625 ln 4)).
    x = np.array([[1.0], [0.0], [1.0]])
    np.testing.assert_allclose(plug_in_bets(x), [2.402245, 1.706683, 1.132429], rtol=1e-6)
    # At alpha 0.05 the bets are scaled by sqrt(2 ln 40) = 2.716203: 6.52498, 4.63570, 3.07591. Against m = 0.1
    # the first is truncated at c / m = 5: (1 + 5 * 0.9) (1 - 4.63570 * 0.1) (1 + 3.07591 * 0.9) = 11.11792.
    bets = np.sqrt(2 * np.log(40)) * plug_in_bets(x)
    assert TRUNCATION == 0.5
    log_capital = _log_capital_above(x, bets, np.full(3, 0.1))
    np.testing.assert_allclose(np.exp(log_capital), [5.5, 5.5 * 0.536430, 11.11792], rtol=1e-5)
    # theta K+ = 5.56 < 20 (and theta K- < 1): 0.1 is inside the sequence after three rounds, as is 0.5.
    low, high = mean_sequence(x, 0.05)
    assert low[-1] < 0.1 < 0.5 < high[-1]


def test_the_ends_are_where_the_hedged_capital_crosses_one_over_alpha():
    rng = np.random.default_rng(3)
    x = (rng.random((12, 4)) < np.array([0.9, 0.6, 0.8, 0.95])).astype(float)
    alpha = 0.05
    low, high = mean_sequence(x, alpha)
    bets = np.sqrt(2 * np.log(2 / alpha)) * plug_in_bets(x)
    # Before the running intersection, each round's lower end is where 1/2 K+ crosses 1/alpha.
    assert HEDGE == 0.5
    raw_low = _lower_ends(x, bets, alpha, HEDGE)
    assert (raw_low > 0).sum() >= 6
    for r in np.flatnonzero(raw_low > 0):
        capital = lambda m: np.log(0.5) + _log_capital_above(x, bets, np.full(12, m))[r]  # noqa: E731
        assert capital(raw_low[r] - 1e-6) >= np.log(1 / alpha) > capital(raw_low[r] + 1e-6)
    np.testing.assert_array_equal(low, np.maximum.accumulate(raw_low))
    # K- on x is K+ on 1 - x: the upper end mirrors.
    mirrored_low, _ = mean_sequence(1 - x, alpha)
    np.testing.assert_allclose(1 - high, mirrored_low, atol=1e-9)
    assert (np.diff(low) >= 0).all() and (np.diff(high) <= 0).all()  # running intersections
    assert low[-1] <= x.mean() <= high[-1]


def test_contrast_and_rate_intervals_are_in_points_and_symmetric():
    rng = np.random.default_rng(0)
    differences = rng.integers(-1, 2, (20, 10)).astype(float)
    forward, backward = contrast_interval(differences, 0.05), contrast_interval(-differences, 0.05)
    assert forward.estimate == pytest.approx(100 * differences.mean())
    assert (forward.low, forward.high) == pytest.approx((-backward.high, -backward.low), abs=1e-6)
    assert contrast_interval(np.zeros((20, 10)), 0.05).low < 0 < contrast_interval(np.zeros((20, 10)), 0.05).high
    outcomes = (rng.random((20, 10)) < 0.7).astype(float)
    rate = rate_interval(outcomes, 0.05)
    assert 0 <= rate.low < rate.estimate < rate.high <= 100 and rate.rounds == 20
    with pytest.raises(ValueError, match=r"in \[0, 1\]"):
        mean_sequence(differences[None], 0.05)


@pytest.mark.parametrize("delta_pp", [0.0, -5.0, -30.0])
def test_coverage_under_continuous_monitoring_with_the_records_task_heterogeneity(paper, delta_pp):
    contrasts, episodes, _ = paper
    result = simulate_coverage([episodes[b] for _, b in contrasts], 25, delta_pp, 0.05, seed=1)
    assert result["sequences"] >= 700
    assert result["coverage"] >= 0.95
    committed = json.loads((ROOT / "benchmarks" / "results" / "sequential_coverage.json").read_text())
    full = {row["delta_pp"]: row for row in committed["coverage"]}[delta_pp]
    assert full["sequences"] >= 10_000 and full["coverage"] >= 1 - committed["alpha"]


def test_at_full_sample_the_sequence_is_at_most_1_6_times_the_bootstrap(paper):
    contrasts, episodes, _ = paper
    ratios = []
    for cell, baseline in contrasts:
        sequence = contrast_interval(paired_rounds(episodes[cell], episodes[baseline]), 0.05)
        interval = task_clustered_bootstrap(episodes[cell], episodes[baseline])
        ratios.append((sequence.high - sequence.low) / (interval.high - interval.low))
    assert np.mean(ratios) <= 1.6


def test_e_bh_rejects_the_largest_e_values_above_its_step_threshold():
    # K = 4 at level 0.1: thresholds K / (level k) = 40, 20, 13.3, 10 for k = 1..4. Sorted e: 100, 50, 12, 11:
    # e_(2) = 50 >= 20, e_(3) = 12 < 13.3, e_(4) = 11 >= 10: k = 4, so all four are rejected.
    assert e_bh(np.log([11, 100, 12, 50]), 0.1).tolist() == [True, True, True, True]
    # 100, 50, 12, 9: e_(4) = 9 < 10 and e_(3) < 13.3: k = 2.
    assert e_bh(np.log([9, 100, 12, 50]), 0.1).tolist() == [False, True, False, True]
    assert not e_bh(np.log([39, 1, 1, 1]), 0.1).any()


def test_the_study_level_changes_no_clear_decision_of_tab_clustered(paper):
    contrasts, episodes, clustered = paper
    differences = [paired_rounds(episodes[a], episodes[b]) for a, b in contrasts]
    design = Design()
    per_contrast, used = study_level(differences, design, "none")
    bootstrap = bootstrapper(clustered.bootstrap)
    intervals = {pair: bootstrap(episodes[pair[0]], episodes[pair[1]]) for pair in clustered.contrasts()}
    clear = {pair for pair, interval in intervals.items() if interval.high < -10 or interval.low > 10}
    assert len(clear) >= 10
    for family in ("e_bh", "split"):
        decisions, study_used = study_level(differences, design, family)
        changed = {pair for pair, before, after in zip(contrasts, per_contrast, decisions) if before != after}
        assert not changed & clear, (family, changed & clear)
        assert sum(study_used) >= sum(used)  # a stricter level reads at least as many episodes
    # e-BH keeps at least every decision the split level makes (the same stops, rejected at K / alpha or below).
    split, _ = study_level(differences, design, "split")
    e_bh_decided, _ = study_level(differences, design, "e_bh")
    assert all(e == s for e, s in zip(e_bh_decided, split) if s != "undecided")


def test_the_live_table_prints_sequences_for_the_stopped_cell_and_no_fixed_sample_interval():
    definition = load_table(ROOT / "config/trained_sequential/tables/trained_sequential.yaml")
    text = render_latex(definition, read_cells(definition.refs(), find_cells(LIVE)))
    rows = {line.split(" & ")[0]: line.rstrip(" \\").split(" & ") for line in text.splitlines() if " & " in line}
    stopped, capped = rows["RTN W2A2, end to end"], rows["RTN W4A8, end to end"]
    header = rows["Cell"]
    bootstrap, sequence, delta = (header.index(name) for name in
                                  (r"$\Delta$, bootstrap 95\%", r"$\Delta$, anytime CS", r"$\Delta$ vs. FP"))
    assert stopped[bootstrap] == "--" and stopped[sequence].startswith("[")
    assert capped[bootstrap].startswith("[") and capped[sequence].startswith("[")
    # Paired: the stopped cell's 36 episodes against the baseline's of the same 12 rounds, not all 60.
    cell, baseline = read_cell(LIVE / STOPPED), read_cell(LIVE / BASELINE)
    rounds = cell.header["stopping"]["rounds_used"]
    same_rounds = baseline.episodes[baseline.episodes["episode"] < rounds]
    paired = 100 * (cell.episodes["success"].mean() - same_rounds["success"].mean())
    unpaired = 100 * (cell.episodes["success"].mean() - baseline.episodes["success"].mean())
    assert float(stopped[delta]) == pytest.approx(paired, abs=0.05) and abs(paired - unpaired) > 1
    assert "No study-level adjustment" in text and "confidence sequence" in text


def test_summary_gives_sequences_and_no_wilson_bounds_for_the_stopped_cell():
    cells = {ref: read_cell(path) for ref, path in find_cells(LIVE).items()}
    summary = summarize(cells).set_index("cell")
    stopped, capped = summary.loc["rtn-W2A2-e2e"], summary.loc["rtn-W4A8-e2e"]
    assert pd.isna(stopped["ci_low"]) and pd.isna(stopped["ci_high"])
    assert stopped["delta_anytime_cs_low_pp"] < stopped["delta_at_stop_pp"] < stopped["delta_anytime_cs_high_pp"] < 0
    assert stopped["rate_anytime_cs_low"] < stopped["success_rate"] < stopped["rate_anytime_cs_high"]
    assert not pd.isna(capped["ci_low"]) and capped["rate_anytime_cs_low"] < capped["ci_low"]  # Wilson and CS beside
    assert pd.isna(summary.loc["rtn-BASELINE-e2e", "rate_anytime_cs_low"])
    expected = rate_interval(outcome_rounds(cells[STOPPED].episodes)[:12], 0.05)
    assert stopped["rate_anytime_cs_low"] == pytest.approx(expected.low, abs=0.01)


def test_cli_on_live_records_leaves_the_full_sample_columns_of_a_stopped_cell_empty(tmp_path):
    out = tmp_path / "live.csv"
    assert main(["sequential", str(LIVE), "--baseline", "rtn-BASELINE-e2e", "--csv", str(out)]) == 0
    rows = {row["cell"]: row for row in csv.DictReader(out.open())}
    assert rows[STOPPED]["full_sample_bootstrap_low_pp"] == "" and rows[STOPPED]["full_sample_decision"] == ""
    assert rows[STOPPED]["decision"] == "worse" and float(rows[STOPPED]["anytime_cs_high_pp"]) < 0
    assert rows[CAPPED]["full_sample_bootstrap_low_pp"] != "" and rows[CAPPED]["anytime_cs_low_pp"] != ""
    assert main(["sequential", str(LIVE), "--baseline", "rtn-BASELINE-e2e", "--family", "holm", "--csv", str(out)]) == 2


def test_retrospective_study_decisions_follow_the_option(paper):
    contrasts, episodes, _ = paper
    picked = contrasts[:6]
    none = retrospective(picked, episodes, family="none")
    assert (none["study_decision"] == none["decision"]).all()
    assert (none["study_episodes_used"] == none["episodes_used"]).all()
    split = retrospective(picked, episodes, family="split")
    assert (split["study_episodes_used"] >= split["episodes_used"]).all()
    assert (split[["decision", "episodes_used"]] == none[["decision", "episodes_used"]]).all().all()
