"""Statistics the paper reports: Wilson intervals, the task-clustered bootstrap, Spearman.

Rates and interval endpoints are returned in percent (pp for contrasts), as printed in the tables.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy.stats import norm, spearmanr
from statsmodels.stats.proportion import proportion_confint

from vlaquantbench.errors import UserError

BOOTSTRAP_DRAWS = 5000
BOOTSTRAP_SEED = 0


# The paper's Wilson interval uses z = 1.96 exactly (App. "Replication and Uncertainty"). statsmodels'
# alpha=0.05 means z = 1.95996..., which moves 6 of the authors' 417 two-decimal bounds by 0.01.
WILSON_Z = 1.96


def wilson_interval(successes, episodes, z: float = WILSON_Z) -> tuple[np.ndarray, np.ndarray]:
    """Wilson score interval (95% at z = 1.96) in percent; accepts scalars or arrays."""
    alpha = 2.0 * norm.sf(z)
    low, high = proportion_confint(np.asarray(successes), np.asarray(episodes), alpha=alpha, method="wilson")
    return 100.0 * np.asarray(low), 100.0 * np.asarray(high)


@dataclass(frozen=True)
class Contrast:
    """A - B in pp with the bootstrap's 2.5/97.5 percentiles."""

    delta: float
    low: float
    high: float


def _task_outcomes(episodes: pd.DataFrame, tasks: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """Outcomes as a (task, episode) matrix padded with zeros, and each task's episode count."""
    groups = [episodes.loc[episodes["task_id"] == task, "success"].to_numpy(dtype=float) for task in tasks]
    counts = np.array([len(group) for group in groups])
    outcomes = np.zeros((len(tasks), counts.max()))
    for row, group in enumerate(groups):
        outcomes[row, : len(group)] = group
    return outcomes, counts


def _resampled_task_rates(outcomes: np.ndarray, counts: np.ndarray, picks: np.ndarray, rng) -> np.ndarray:
    """Success rate of each picked task after resampling its episodes with replacement: (draws, tasks)."""
    picked_counts = counts[picks][..., None]
    width = outcomes.shape[1]
    # floor(u * n) is a uniform episode index per task; several times faster than integers() with array bounds
    episodes = (rng.random((*picks.shape, width)) * picked_counts).astype(np.int64)
    valid = np.arange(width) < picked_counts  # tasks with fewer episodes use only their first n slots
    drawn = outcomes[picks[..., None], episodes] * valid
    return drawn.sum(axis=-1) / picked_counts[..., 0]


def task_clustered_bootstrap(
    a: pd.DataFrame, b: pd.DataFrame, draws: int = BOOTSTRAP_DRAWS, seed: int = BOOTSTRAP_SEED
) -> Contrast:
    """The paper's two-stage percentile bootstrap for the success-rate contrast A - B.

    Each draw resamples the task identities with replacement (the same identities for both cells),
    then resamples episodes within each selected task independently per cell, and averages the
    task-wise differences with equal task weight. All draws are one array operation.
    """
    tasks_a, tasks_b = sorted(a["task_id"].unique()), sorted(b["task_id"].unique())
    if tasks_a != tasks_b:
        raise UserError(f"bootstrap contrast needs the same tasks in both cells: {tasks_a} vs {tasks_b}")
    rng = np.random.default_rng(seed)
    picks = rng.integers(0, len(tasks_a), size=(draws, len(tasks_a)))
    rate_a, rate_b = (_resampled_task_rates(*_task_outcomes(cell, tasks_a), picks, rng) for cell in (a, b))
    differences = 100.0 * (rate_a - rate_b).mean(axis=1)
    low, high = np.percentile(differences, [2.5, 97.5])
    delta = 100.0 * (a["success"].mean() - b["success"].mean())
    return Contrast(delta=float(delta), low=float(low), high=float(high))


def spearman(x, y) -> float:
    """Spearman rank correlation; ties get average ranks."""
    return float(spearmanr(x, y).statistic)
