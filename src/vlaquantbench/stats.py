"""Statistics the paper reports: Wilson intervals, the task-clustered bootstrap, Spearman.

Rates and interval endpoints are returned in percent (pp for contrasts), as printed in the tables.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from vlaquantbench.errors import UserError

BOOTSTRAP_DRAWS = 5000
BOOTSTRAP_SEED = 0


# The paper's Wilson interval uses z = 1.96 exactly (App. "Replication and Uncertainty"). statsmodels'
# alpha=0.05 means z = 1.95996..., which moves 6 of the authors' 417 two-decimal bounds by 0.01.
WILSON_Z = 1.96


def wilson_interval(successes, episodes, z: float = WILSON_Z) -> tuple[np.ndarray, np.ndarray]:
    """Wilson score interval (95% at z = 1.96) in percent; accepts scalars or arrays."""
    # imported here: scipy.stats and statsmodels take seconds to import, and most table jobs need neither
    from scipy.stats import norm
    from statsmodels.stats.proportion import proportion_confint

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


def _draw_indices(rng: np.random.Generator, draws: int, counts_a: np.ndarray, counts_b: np.ndarray):
    """Task picks (draws, T) and episode indices (draws, T, width) for A and B, from `rng` in the paper's order.

    The order of one draw is: T task indices, then for each picked task A's episode indices followed
    by B's (each `integers(0, n, n)` with n that task's episode count). numpy draws bounded integers
    from one 32-bit stream whichever way the bounds are batched, so one `integers` call over the
    concatenated bounds consumes `rng` exactly as the draw-by-draw calls do, rejections included.
    """
    tasks, width_a, width_b = len(counts_a), counts_a.max(), counts_b.max()
    if len(set(counts_a)) == 1 and len(set(counts_b)) == 1:  # every task the same size: one call for all draws
        per_task = np.r_[np.full(width_a, width_a), np.full(width_b, width_b)]
        bounds = np.r_[np.full(tasks, tasks), np.tile(per_task, tasks)]
        values = rng.integers(0, np.tile(bounds, draws)).reshape(draws, -1)
        episodes = values[:, tasks:].reshape(draws, tasks, width_a + width_b)
        return values[:, :tasks], episodes[..., :width_a], episodes[..., width_a:]
    picks = np.empty((draws, tasks), dtype=np.int64)
    index_a = np.zeros((draws, tasks, width_a), dtype=np.int64)
    index_b = np.zeros((draws, tasks, width_b), dtype=np.int64)
    for draw in range(draws):  # the bounds of a draw depend on its picks
        picks[draw] = rng.integers(0, tasks, tasks)
        sizes = np.stack([counts_a[picks[draw]], counts_b[picks[draw]]], axis=1).ravel()
        segments = np.split(rng.integers(0, np.repeat(sizes, sizes)), np.cumsum(sizes)[:-1])
        for slot, (drawn_a, drawn_b) in enumerate(zip(segments[0::2], segments[1::2])):
            index_a[draw, slot, : len(drawn_a)], index_b[draw, slot, : len(drawn_b)] = drawn_a, drawn_b
    return picks, index_a, index_b


def _resampled_task_rates(outcomes: np.ndarray, counts: np.ndarray, picks: np.ndarray, episodes: np.ndarray):
    """Success rate of each picked task over its resampled episodes: (draws, tasks)."""
    picked_counts = counts[picks][..., None]
    valid = np.arange(episodes.shape[-1]) < picked_counts  # tasks with fewer episodes use only their first n slots
    drawn = outcomes[picks[..., None], episodes] * valid
    return drawn.sum(axis=-1) / picked_counts[..., 0]


def task_clustered_bootstrap(
    a: pd.DataFrame,
    b: pd.DataFrame,
    draws: int = BOOTSTRAP_DRAWS,
    seed: int = BOOTSTRAP_SEED,
    rng: np.random.Generator | None = None,
) -> Contrast:
    """The paper's two-stage percentile bootstrap for the success-rate contrast A - B.

    Each draw resamples the task identities with replacement (the same identities for both cells),
    then, for each picked task, resamples A's episodes and then B's with replacement, and averages
    the task-wise differences with equal task weight; the interval is numpy's default (linear)
    2.5/97.5 percentiles of 100 x that mean. `rng` continues a stream shared with other contrasts
    (the paper's tab:clustered draws its 30 rows from one `default_rng(0)` in row order); without
    it the contrast uses its own `default_rng(seed)`.
    """
    tasks_a, tasks_b = sorted(a["task_id"].unique()), sorted(b["task_id"].unique())
    if tasks_a != tasks_b:
        raise UserError(f"bootstrap contrast needs the same tasks in both cells: {tasks_a} vs {tasks_b}")
    rng = np.random.default_rng(seed) if rng is None else rng
    (outcomes_a, counts_a), (outcomes_b, counts_b) = _task_outcomes(a, tasks_a), _task_outcomes(b, tasks_a)
    picks, episodes_a, episodes_b = _draw_indices(rng, draws, counts_a, counts_b)
    rate_a = _resampled_task_rates(outcomes_a, counts_a, picks, episodes_a)
    rate_b = _resampled_task_rates(outcomes_b, counts_b, picks, episodes_b)
    differences = 100.0 * (rate_a - rate_b).mean(axis=1)
    low, high = np.percentile(differences, [2.5, 97.5])
    delta = 100.0 * (a["success"].mean() - b["success"].mean())
    return Contrast(delta=float(delta), low=float(low), high=float(high))


@dataclass(frozen=True)
class ClusteredMean:
    """The mean over episodes of a per-episode number, with the task-clustered bootstrap's 2.5/97.5 percentiles."""

    mean: float
    low: float
    high: float


def task_clustered_mean(episodes: pd.DataFrame, column: str, draws: int = BOOTSTRAP_DRAWS,
                        seed: int = BOOTSTRAP_SEED) -> ClusteredMean:
    """The one-cell analogue of `task_clustered_bootstrap` for a per-episode number (jerk, action rate): each
    draw resamples the task identities with replacement, then each picked task's episodes, and averages the
    task means with equal task weight; episodes whose value is missing (null) are left out. The point estimate
    is the plain mean over episodes, as the success rate is."""
    present = episodes.dropna(subset=[column])
    tasks = sorted(present["task_id"].unique())
    groups = [present.loc[present["task_id"] == task, column].to_numpy(dtype=float) for task in tasks]
    counts = np.array([len(group) for group in groups])
    values = np.zeros((len(tasks), counts.max()))
    for row, group in enumerate(groups):
        values[row, : len(group)] = group
    rng = np.random.default_rng(seed)
    picks = rng.integers(0, len(tasks), (draws, len(tasks)))
    # Episode indices below each picked task's count (a task with fewer episodes uses its first n slots).
    drawn = rng.integers(0, np.broadcast_to(counts[picks][..., None], (draws, len(tasks), counts.max())))
    task_means = _resampled_task_rates(values, counts, picks, drawn).mean(axis=1)
    low, high = np.percentile(task_means, [2.5, 97.5])
    return ClusteredMean(mean=float(present[column].mean()), low=float(low), high=float(high))


def spearman(x, y) -> float:
    """Spearman rank correlation; ties get average ranks."""
    from scipy.stats import spearmanr

    return float(spearmanr(x, y).statistic)
