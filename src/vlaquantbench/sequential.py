"""Sequential evaluation: stop a cell's contrast with its baseline as soon as its answer is known.

The stopping rule is an anytime-valid test of A - B, the difference in success rates between a cell A
and its baseline B, at a declared alpha and a maximum episode count (the cells' recorded episodes).
Episodes are taken in the task-interleaved order: round k holds episode k of every task of both cells,
so every prefix of whole rounds is balanced over tasks. After each round it decides

- `worse`: A is worse than B (H0: A - B >= 0 rejected),
- `not_worse`: A is not worse than B by more than the margin (H0: A - B <= -margin rejected),
- or continues; `undecided` when the cap is reached first.

Each decision is a one-sided test by betting (Waudby-Smith & Ramdas, JRSS-B 2024): on the paired
differences mapped to [0, 1], x = (a - b + 1) / 2, with mean theta = (Delta + 1) / 2, the capital
prod (1 + lambda_r (x - theta0)) of a bet lambda_r >= 0 fixed for a round from the earlier rounds
(aGRAPA) is a test supermartingale under H0: theta <= theta0, so by Ville's inequality it exceeds
1/alpha with probability at most alpha at any round, whenever the test stops. The two nulls
(Delta >= 0 and Delta <= -margin) are disjoint, so at any Delta at most one decision is false: the
false-decision probability is at most alpha, not 2 alpha.

What the guarantee assumes about tasks. The tasks are fixed: the estimand is Delta, the mean over the
suite's tasks of each task's difference in success probability (the paper's point estimate), not a
difference over a population of tasks from which these were drawn (what the paper's task-clustered
bootstrap interval also covers). Within a task, episodes are exchangeable (each init state and seed one
draw from the task's distribution) and outcomes are independent given their task. Tasks may differ
arbitrarily: within a round each task's episode has its own mean, and by the AM-GM inequality the
expected capital of a round is at most (1 + lambda (mean of the round's means - theta0))^T <= 1 under
H0, because every round visits every task once. `simulate_false_decisions` checks the rate on the
authors' records under their task heterogeneity.

Estimates at the stop. A cell's interval at the round the rule stopped is a confidence sequence
(`vlaquantbench.confidence_sequence`), time-uniform and so valid at that data-chosen round, for A - B paired
over the rounds the rule read (never against the baseline's other episodes) and for A's own success rate.
Fixed-sample intervals (the task-clustered bootstrap, Wilson) are printed only over records that ran in full.

A study's guarantee (`FAMILIES`): each contrast's decision is at alpha on its own (`none`); `e_bh` keeps the
rule and its stops and makes a study's decisions by e-BH (Wang & Ramdas, JRSS-B 2022) on the capitals at the
stops, e-values for their nulls by optional stopping, for a false-discovery rate at most alpha over the study;
`split` runs every contrast at alpha / K (K contrasts), a family-wise error rate at most alpha, its intervals at
1 - alpha / K (simultaneous coverage at least 1 - alpha).

Why not a library's test. confseq (MIT) has betting confidence sequences but ships only an sdist that does
not build or import here: it pins pybind11 ~= 2.6, which does not compile against Python 3.12 (even with
Boost's headers installed), and its modules annotate with `np.float_`, removed in NumPy 2. `expectation` is
GPL-3.0 with an AI-training restriction (not usable from this MIT project); STEP
(`sequentialized-barnard-tests`) is CC-BY-NC-4.0 and tests i.i.d. Bernoulli pairs for superiority only (no
margin, no task rounds). The bet and the capital are a few lines of numpy, vectorized over simulated
contrasts; tests/test_confidence_sequence.py checks them against capitals computed by hand.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Collection, Mapping

import numpy as np
import pandas as pd

from vlaquantbench.atomic import write_text
from vlaquantbench.confidence_sequence import AnytimeInterval, contrast_interval, mean_sequence, rate_interval
from vlaquantbench.errors import UserError
from vlaquantbench.stats import task_clustered_bootstrap

DECISIONS = ("worse", "not_worse", "undecided")
DEFAULT_ALPHA = 0.05
# The paper calls a subset "within 5 pp" of its baseline (tab:c2); the same tolerance defines `not_worse`.
DEFAULT_MARGIN_PP = 5.0
# Bets are at most this fraction of the largest bet that keeps the capital positive (1 / theta0).
BET_TRUNCATION = 0.5
# The study-level guarantee: none (each decision at alpha), e-BH on the capitals (false-discovery rate), alpha
# split over the study's contrasts (family-wise error rate).
FAMILIES = ("none", "e_bh", "split")
DEFAULT_FAMILY = "e_bh"
# `full_sample_*`: the fixed design over all recorded episodes (empty where the records were stopped early);
# `*_at_stop` with `anytime_cs_*`: paired over the rounds the rule read, with the confidence sequence there.
CSV_COLUMNS = ("cell", "baseline", "episodes_used", "episodes_available", "decision", "full_sample_decision",
               "study_decision", "study_episodes_used", "rounds_used", "full_sample_rate", "full_sample_baseline_rate", "full_sample_delta_pp",
               "full_sample_bootstrap_low_pp", "full_sample_bootstrap_high_pp", "delta_at_stop_pp",
               "anytime_cs_low_pp", "anytime_cs_high_pp", "rate_at_stop", "rate_anytime_cs_low", "rate_anytime_cs_high",
               "log_capital_worse", "log_capital_not_worse", "agrees")


@dataclass(frozen=True)
class Design:
    """The stopping rule's declared level and margin (pp); the cap is the paired rounds recorded."""

    alpha: float = DEFAULT_ALPHA
    margin_pp: float = DEFAULT_MARGIN_PP

    def __post_init__(self):
        if not 0.0 < self.alpha < 1.0:
            raise UserError(f"alpha must lie in (0, 1), got {self.alpha}")
        if not 0.0 < self.margin_pp < 100.0:
            raise UserError(f"margin must lie in (0, 100) pp, got {self.margin_pp}")


@dataclass(frozen=True)
class SequentialResult:
    decision: str
    rounds_used: int
    tasks: int
    log_capital_worse: float  # the two tests' state when the rule stopped
    log_capital_not_worse: float

    @property
    def episodes_used(self) -> int:
        """Episodes of each cell the rule consumed (the baseline's are paired with them)."""
        return self.rounds_used * self.tasks


def interleaved_order(episodes: pd.DataFrame) -> pd.DataFrame:
    """The cell's episodes round-robin over tasks: round k is the k-th episode of every task, in task order."""
    ranked = episodes.assign(_round=episodes.groupby("task_id")["episode"].rank(method="first").astype(int) - 1)
    return ranked.sort_values(["_round", "task_id"], kind="stable").reset_index(drop=True)


def outcome_rounds(episodes: pd.DataFrame) -> np.ndarray:
    """Successes as a (round, task) matrix in the interleaved order, over the rounds with every task's episode."""
    grid = interleaved_order(episodes).pivot(index="_round", columns="task_id", values="success").astype(float)
    return grid.to_numpy()[: int(grid.notna().all(axis=1).cumprod().sum())]


def paired_rounds(a: pd.DataFrame, b: pd.DataFrame, names: tuple[str, str] = ("A", "B")) -> np.ndarray:
    """Differences a - b as a (round, task) matrix in the interleaved order, over the rounds in which both
    cells recorded every task (a cell with 19 episodes on some task has 19 complete rounds)."""
    tasks_a, tasks_b = sorted(a["task_id"].unique()), sorted(b["task_id"].unique())
    if tasks_a != tasks_b:
        raise UserError(f"{names[0]} and {names[1]} record different tasks ({tasks_a} vs {tasks_b}); "
                        "a contrast needs the same tasks in both cells")
    grid_a, grid_b = outcome_rounds(a), outcome_rounds(b)
    complete = min(len(grid_a), len(grid_b))
    if complete == 0:
        raise UserError(f"{names[0]} and {names[1]} share no round with an episode of every task")
    return grid_a[:complete] - grid_b[:complete]


def log_capital(x: np.ndarray, theta0: float) -> np.ndarray:
    """Log capital after each round of the bet against H0: mean(x) <= theta0, for `x` of shape
    (..., rounds, tasks) in [0, 1]; the bet of a round (aGRAPA, truncated) uses the earlier rounds only."""
    rounds, tasks = x.shape[-2:]
    shape = x.shape[:-2]
    total, squares, seen = np.zeros(shape), np.zeros(shape), 0
    capital, path = np.zeros(shape), np.empty(shape + (rounds,))
    for index in range(rounds):
        # Shrunk towards the uninformative 1/2 and 1/4 so the first bets are finite and small.
        mean = (0.5 + total) / (1 + seen)
        variance = (0.25 + squares - 2 * mean * total + seen * mean**2) / (1 + seen)
        edge = mean - theta0
        bet = np.clip(edge / (variance + edge**2), 0.0, BET_TRUNCATION / theta0)
        block = x[..., index, :]
        capital = capital + np.log1p(bet[..., None] * (block - theta0)).sum(axis=-1)
        path[..., index] = capital
        total, squares, seen = total + block.sum(axis=-1), squares + (block**2).sum(axis=-1), seen + tasks
    return path


def _decide(differences: np.ndarray, design: Design):
    """Decision index (into DECISIONS), stopping round (1-based) and both log capitals, per contrast of
    `differences` (..., rounds, tasks)."""
    x = (differences + 1.0) / 2.0
    worse = log_capital(1.0 - x, 0.5)  # H0: Delta >= 0
    not_worse = log_capital(x, (1.0 - design.margin_pp / 100.0) / 2.0)  # H0: Delta <= -margin
    threshold = np.log(1.0 / design.alpha)
    crossed = (worse >= threshold) | (not_worse >= threshold)
    rounds = differences.shape[-2]
    stop = np.where(crossed.any(axis=-1), crossed.argmax(axis=-1), rounds - 1)
    at_stop = lambda path: np.take_along_axis(path, stop[..., None], axis=-1)[..., 0]  # noqa: E731
    capital_worse, capital_not_worse = at_stop(worse), at_stop(not_worse)
    # `worse` first when both cross in one round: A is then worse, by less than the margin.
    decision = np.where(capital_worse >= threshold, 0, np.where(capital_not_worse >= threshold, 1, 2))
    return decision, stop + 1, capital_worse, capital_not_worse


def stopping_rule(differences: np.ndarray, design: Design = Design()) -> SequentialResult:
    """Run the rule over a (round, task) matrix of paired differences a - b in {-1, 0, 1}."""
    decision, rounds, worse, not_worse = _decide(np.asarray(differences, dtype=float), design)
    return SequentialResult(DECISIONS[int(decision)], int(rounds), differences.shape[1], float(worse), float(not_worse))


def full_sample_decision(low_pp: float, high_pp: float, design: Design) -> str:
    """The fixed design's decision from a 95% interval of A - B (pp), by the same precedence as the rule."""
    if high_pp < 0:
        return "worse"
    return "not_worse" if low_pp > -design.margin_pp else "undecided"


def contrast_row(cell: str, baseline: str, a: pd.DataFrame, b: pd.DataFrame, design: Design,
                 stopped_early: bool = False) -> dict:
    """One contrast: the stopping rule on the interleaved episodes, A - B and A's success rate at its stop (paired
    over the rounds it read, with their confidence sequences at its level) and the full-sample clustered
    bootstrap (5,000 draws, its own `default_rng(0)`, so a row does not depend on the others). `stopped_early`:
    A's records are what a live rule ran, a count its data chose, so no fixed-sample column is filled."""
    differences = paired_rounds(a, b, (cell, baseline))
    result = stopping_rule(differences, design)
    at_stop = contrast_interval(differences[: result.rounds_used], design.alpha)
    rate = rate_interval(outcome_rounds(a)[: result.rounds_used], design.alpha)
    row = {
        "cell": cell, "baseline": baseline, "episodes_used": result.episodes_used, "episodes_available": len(a),
        "decision": result.decision, "rounds_used": result.rounds_used, "delta_at_stop_pp": at_stop.estimate,
        "anytime_cs_low_pp": at_stop.low, "anytime_cs_high_pp": at_stop.high, "rate_at_stop": rate.estimate,
        "rate_anytime_cs_low": rate.low, "rate_anytime_cs_high": rate.high,
        "log_capital_worse": result.log_capital_worse, "log_capital_not_worse": result.log_capital_not_worse,
    }
    if stopped_early:  # nothing to contradict
        return {**row, "full_sample_decision": "", "agrees": True}
    interval = task_clustered_bootstrap(a, b)
    full = full_sample_decision(interval.low, interval.high, design)
    return {
        **row, "full_sample_decision": full, "full_sample_rate": 100.0 * a["success"].mean(),
        "full_sample_baseline_rate": 100.0 * b["success"].mean(), "full_sample_delta_pp": interval.delta,
        "full_sample_bootstrap_low_pp": interval.low, "full_sample_bootstrap_high_pp": interval.high,
        # A "no decision" at the cap agrees with anything; two decisions agree when they are the same.
        "agrees": "undecided" in (result.decision, full) or result.decision == full,
    }


def e_bh(log_e_values: np.ndarray, level: float) -> np.ndarray:
    """Wang & Ramdas' e-BH at `level` on K e-values (given as logs): reject the k largest, k the largest with
    e_(k) >= K / (level k). Its false-discovery rate is at most level K0 / K (K0 true nulls) under any
    dependence between the e-values. A boolean mask of the rejected."""
    log_e = np.asarray(log_e_values, dtype=float)
    ranked = np.sort(log_e)[::-1]
    passing = np.flatnonzero(ranked >= np.log(log_e.size / (level * np.arange(1, log_e.size + 1))))
    if passing.size == 0:
        return np.zeros(log_e.size, dtype=bool)
    return log_e >= ranked[passing[-1]]


def e_bh_decisions(log_capital_worse: np.ndarray, log_capital_not_worse: np.ndarray, alpha: float) -> np.ndarray:
    """The study's decisions by e-BH on both tests' capitals at each contrast's stop (an e-value for its null by
    optional stopping). A contrast's two nulls are disjoint, so at most K of the 2K are true: e-BH at 2 alpha
    over the 2K e-values has FDR <= 2 alpha K / 2K = alpha, with e-BH-at-alpha-on-K's threshold K / (alpha k)."""
    contrasts = len(log_capital_worse)
    rejected = e_bh(np.r_[log_capital_worse, log_capital_not_worse], 2.0 * alpha)
    worse, not_worse = rejected[:contrasts], rejected[contrasts:]
    # `worse` first when both are rejected, as the rule does.
    return np.where(worse, "worse", np.where(not_worse, "not_worse", "undecided"))


def study_design(design: Design, family: str, contrasts: int) -> Design:
    """The level each of a study's K contrasts runs at: alpha / K under a study-level option, else alpha.

    Under `e_bh` too: a rule that stops at a capital of 1/alpha leaves e-values just above 1/alpha, which e-BH
    over K contrasts rejects only when at least K of them are (k with e_(k) >= K / (alpha k)): on the paper's 40
    contrasts it would reject none. Stopping at K / alpha, e-BH's strictest threshold, every decided contrast is
    rejected whatever the others do, and a contrast undecided at its cap still is when its capital reaches
    K / (alpha k). Each stop depends on its own contrast's episodes alone, so its capital stays an e-value."""
    if family not in FAMILIES:
        raise UserError(f"study-level option must be one of {', '.join(FAMILIES)}, got {family!r}")
    return design if family == "none" else Design(design.alpha / contrasts, design.margin_pp)


def study_guarantee(family: str, design: Design, contrasts: int) -> str:
    """What holds for a study of `contrasts` decisions under `family`, as a sentence (LaTeX)."""
    if family == "none":
        return (f"No study-level adjustment: each of the {contrasts} decisions is at $\\alpha={design.alpha:g}$ on its "
                "own, nothing is claimed for them together.")
    rule = f"each contrast's rule at $\\alpha/{contrasts}={design.alpha / contrasts:.3g}$"
    if family == "e_bh":
        guarantee = (f"{rule} and e-BH (Wang \\& Ramdas) on the capitals at the stops: a false-discovery rate of at "
                     f"most {design.alpha:g} over the {contrasts} contrasts")
    else:
        guarantee = f"$\\alpha={design.alpha:g}$ split, {rule}: a family-wise error rate of at most {design.alpha:g}"
    return f"Study level (column Study): {guarantee}; the intervals are each at $1-\\alpha$."


def study_level(differences: list[np.ndarray], design: Design, family: str) -> tuple[list[str], list[int]]:
    """A study's decisions on its contrasts' paired `differences` under `family`, and the episodes each contrast's
    rule reads for them (its stop at the study's level, `study_design`)."""
    results = [stopping_rule(contrast, study_design(design, family, len(differences))) for contrast in differences]
    decisions = [result.decision for result in results]
    if family == "e_bh":
        decisions = list(e_bh_decisions(np.array([r.log_capital_worse for r in results]),
                                        np.array([r.log_capital_not_worse for r in results]), design.alpha))
    return decisions, [result.episodes_used for result in results]


def retrospective(contrasts: list[tuple[str, str]], episodes: Mapping[str, pd.DataFrame], design: Design = Design(),
                  family: str = DEFAULT_FAMILY, stopped_early: Collection[str] = ()) -> pd.DataFrame:
    """The stopping rule run over recorded cells: one row per (cell, baseline) contrast (CSV_COLUMNS), each contrast
    at `design`'s level, and the study's decisions under `family` with the episodes they read (`study_*`).
    `stopped_early`: cells whose records a live rule stopped before their cap (no fixed-sample column for them)."""
    rows = [contrast_row(cell, baseline, episodes[cell], episodes[baseline], design, cell in stopped_early)
            for cell, baseline in contrasts]
    table = pd.DataFrame(rows, columns=list(CSV_COLUMNS))
    decisions, used = study_level([paired_rounds(episodes[a], episodes[b]) for a, b in contrasts], design, family)
    return table.assign(study_decision=decisions, study_episodes_used=used)


def saved_fraction(table: pd.DataFrame) -> float:
    """Share of the fixed design's episodes (of the contrasted cells) that the rule did not need."""
    return 1.0 - table["episodes_used"].sum() / table["episodes_available"].sum()


def live_episodes(table: pd.DataFrame, workers: int) -> pd.Series:
    """Episodes per contrast that the live runner (`runner.stopping`) runs with `workers` simulator workers per cell:
    it runs batches of ceil(workers / tasks) whole rounds, so a decision inside a batch runs the batch out
    (within the cap); one worker per task or fewer runs exactly `episodes_used`."""
    tasks = table["episodes_used"] // table["rounds_used"]
    batch = np.ceil(workers / tasks)
    rounds = np.minimum(table["episodes_available"] // tasks, np.ceil(table["rounds_used"] / batch) * batch)
    return (rounds * tasks).astype(int)


def ran_in_full(header: Mapping) -> bool:
    """Whether a cell's records are a fixed design's: it ran without the stopping rule, or to the rule's cap."""
    stopping = header.get("stopping")
    return not stopping or stopping["rounds_run"] >= header["episodes_per_task"]


def rounds_read(header: Mapping) -> int:
    """The rounds that the estimates of a cell run under the stopping rule read: up to its stop, or all of them
    where it ran to its cap."""
    stopping = header["stopping"]
    return stopping["rounds_run"] if ran_in_full(header) else stopping["rounds_used"]


def rate_at_stop(episodes: pd.DataFrame, header: Mapping) -> AnytimeInterval:
    """A cell run under the stopping rule (header `stopping`): its success rate over the rounds it read, with its
    confidence sequence at the rule's level there."""
    return rate_interval(outcome_rounds(episodes)[: rounds_read(header)], header["stopping"]["alpha"])


def contrast_at_stop(episodes: pd.DataFrame, header: Mapping, against: pd.DataFrame) -> AnytimeInterval:
    """Its contrast with `against`, paired over the rounds it read (never against B's other episodes), with the
    confidence sequence at the rule's level there."""
    differences = paired_rounds(episodes, against, ("the cell", "its baseline"))[: rounds_read(header)]
    return contrast_interval(differences, header["stopping"]["alpha"])


def write_csv(table: pd.DataFrame, path: str | Path) -> Path:
    write_text(path, table.to_csv(index=False, float_format="%.4f"))
    return Path(path)


# --- error control under the records' task heterogeneity -------------------------------------------


def _permuted_nulls(a: pd.DataFrame, b: pd.DataFrame, count: int, rng: np.random.Generator) -> np.ndarray:
    """`count` null contrasts from one recorded pair: within each task the two cells' outcomes are pooled
    and relabelled at random (so each task's difference is zero in expectation, its rate as recorded), in
    a random episode order; shape (count, rounds, tasks)."""
    tasks = sorted(a["task_id"].unique())
    per_task = min(min((a["task_id"] == t).sum(), (b["task_id"] == t).sum()) for t in tasks)
    nulls = np.empty((count, per_task, len(tasks)))
    for column, task in enumerate(tasks):
        pooled = np.r_[a.loc[a["task_id"] == task, "success"].to_numpy(float)[:per_task],
                       b.loc[b["task_id"] == task, "success"].to_numpy(float)[:per_task]]
        shuffled = rng.permuted(np.broadcast_to(pooled, (count, pooled.size)), axis=1)
        nulls[:, :, column] = shuffled[:, :per_task] - shuffled[:, per_task:]
    return nulls


def _shifted_contrasts(b: pd.DataFrame, margin: float, count: int, rng: np.random.Generator) -> np.ndarray:
    """`count` contrasts at Delta = -margin exactly from one recorded baseline: B's episodes are drawn
    from its per-task rates p, A's from q = max(p - s, 0) with s set so mean(q) = mean(p) - margin (the
    recorded heterogeneity, shifted); independent Bernoulli episodes. None when the baseline's rate is below
    the margin."""
    rates = b.groupby("task_id")["success"].mean().to_numpy(float)
    per_task = int(b.groupby("task_id").size().min())
    if rates.mean() < margin:
        return None
    from scipy.optimize import brentq

    shift = brentq(lambda s: np.maximum(rates - s, 0).mean() - (rates.mean() - margin), 0.0, 1.0)
    shifted = np.maximum(rates - shift, 0)
    draws_b = rng.random((count, per_task, len(rates))) < rates
    draws_a = rng.random((count, per_task, len(rates))) < shifted
    return draws_a.astype(float) - draws_b.astype(float)


def simulate_false_decisions(pairs: list[tuple[pd.DataFrame, pd.DataFrame]], per_pair: int, design: Design = Design(),
                             seed: int = 0) -> dict:
    """False-decision rates of the rule on simulated contrasts built from recorded pairs (A, B):
    `per_pair` permutation nulls (Delta = 0: `worse` is false) and `per_pair` boundary nulls at
    Delta = -margin (`not_worse` is false) per pair."""
    rng = np.random.default_rng(seed)
    counts = {"zero_difference": [0, 0], "margin_boundary": [0, 0]}
    for a, b in pairs:
        decision, *_ = _decide(_permuted_nulls(a, b, per_pair, rng), design)
        counts["zero_difference"][0] += int((decision == DECISIONS.index("worse")).sum())
        counts["zero_difference"][1] += per_pair
        boundary = _shifted_contrasts(b, design.margin_pp / 100.0, per_pair, rng)
        if boundary is not None:
            decision, *_ = _decide(boundary, design)
            counts["margin_boundary"][0] += int((decision == DECISIONS.index("not_worse")).sum())
            counts["margin_boundary"][1] += per_pair
    return {
        "design": asdict(design), "seed": seed, "pairs": len(pairs), "per_pair": per_pair,
        **{name: {"contrasts": total, "false_decisions": false, "rate": false / total}
           for name, (false, total) in counts.items()},
    }


def simulate_coverage(baselines: list[pd.DataFrame], per_baseline: int, delta_pp: float, alpha: float = DEFAULT_ALPHA,
                      seed: int = 0) -> dict:
    """Coverage of the confidence sequence of A - B under continuous monitoring: the share of simulated contrasts
    whose true Delta lies in the sequence at every round (the running intersection at the last round), `per_baseline`
    contrasts at Delta = `delta_pp` from each recorded baseline's per-task rates (`_shifted_contrasts`; a baseline
    whose rate is below -Delta gives none)."""
    rng = np.random.default_rng(seed)
    truth = (1.0 + delta_pp / 100.0) / 2.0
    covered = total = 0
    for b in baselines:
        contrasts = _shifted_contrasts(b, -delta_pp / 100.0, per_baseline, rng)
        if contrasts is None:
            continue
        low, high = mean_sequence((contrasts + 1.0) / 2.0, alpha)
        covered += int(((low[:, -1] <= truth) & (truth <= high[:, -1])).sum())
        total += per_baseline
    return {"delta_pp": delta_pp, "alpha": alpha, "seed": seed, "sequences": total, "covered": covered,
            "coverage": covered / total}
