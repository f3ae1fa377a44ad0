"""Anytime-valid confidence sequences by betting for the stopping rule's estimands.

A cell the stopping rule stopped recorded as many episodes as its data chose, so a fixed-sample interval
(Wilson, the task-clustered bootstrap) over them loses its coverage. What holds at a data-chosen round is
a confidence sequence: intervals (L_r, U_r) with P(the mean lies in (L_r, U_r) at every round r) >= 1 - alpha,
so in particular at the round the rule stopped.

Construction: Waudby-Smith & Ramdas' hedged capital (JRSS-B 2024, Sec. 4.2, "predictable plug-in" bets) for
the mean m of x in [0, 1], over the task-interleaved rounds the rule reads. Against a candidate m,

    K+_r(m) = prod (1 + min(lambda_s, c / m) (x - m)),  K-_r(m) = prod (1 - min(lambda_s, c / (1 - m)) (x - m)),

over the episodes of rounds s <= r, with c = 1/2 and the hedge K_r(m) = max(theta K+, (1 - theta) K-), theta = 1/2,
which is at most theta K+ + (1 - theta) K-. The bet lambda_s is WSR's plug-in
sqrt(2 log(2 / alpha) / (sigma2 t log(1 + t))), with t the index of the round's first episode and sigma2 their
regularised running variance of the episodes before the round.

Why a bet per round, not per episode: a round holds one episode of each task, and tasks have their own means.
With one bet for the whole round, fixed before it, the round's expected factor is prod_j (1 + lambda (mu_j - m))
<= (1 + lambda (mean_j mu_j - m))^T by the AM-GM inequality: at most 1 when m is the task-averaged mean, the
estimand. So K+ and K- are test supermartingales there (the same argument as the stopping rule's), and by
Ville's inequality K_r(m) stays below 1/alpha at every round with probability at least 1 - alpha.

The set {m : K_r(m) < 1/alpha} is an interval: every factor of K+ is non-increasing in m and every factor of
K- non-decreasing (the plug-in bet does not depend on m), so its lower end is where theta K+ falls below 1/alpha
and its upper end where (1 - theta) K- rises above it. Both are found by bisection to 2^-34, rounded outwards,
and the running intersection over rounds is reported (still a confidence sequence, never wider).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# theta: the weight of the capital betting on a mean above m (the rest bets below): symmetric.
HEDGE = 0.5
# c: bets are at most this fraction of the largest bet that keeps the capital positive, c / m or c / (1 - m).
TRUNCATION = 0.5
BISECTION_STEPS = 34


@dataclass(frozen=True)
class AnytimeInterval:
    """A mean over the rounds read (percent, or pp for a contrast) with its confidence sequence at that round."""

    estimate: float
    low: float
    high: float
    rounds: int


def plug_in_bets(x: np.ndarray) -> np.ndarray:
    """The unscaled bet sqrt(1 / (sigma2 t log(1 + t))) of each round of `x` (..., rounds, tasks), from the episodes
    before the round only (WSR's mean and variance, regularised by one pseudo-episode of mean 1/2, variance 1/4)."""
    rounds, tasks = x.shape[-2:]
    flat = x.reshape(x.shape[:-2] + (rounds * tasks,))
    seen = np.arange(1, rounds * tasks + 1)
    mean = (0.5 + np.cumsum(flat, axis=-1)) / (seen + 1)
    variance = (0.25 + np.cumsum((flat - mean) ** 2, axis=-1)) / (seen + 1)
    # The variance after each earlier round's last episode; 1/4 before the first round.
    before = np.concatenate([np.full(x.shape[:-2] + (1,), 0.25), variance[..., tasks - 1 :: tasks][..., :-1]], axis=-1)
    first = np.arange(rounds) * tasks + 1.0
    return np.sqrt(1.0 / (before * first * np.log1p(first)))


def _log_capital_above(x: np.ndarray, bets: np.ndarray, m: np.ndarray) -> np.ndarray:
    """log K+_r(m_r) for each round r, the capital betting that the mean exceeds m_r, through round r;
    `x` (..., rounds, tasks), `bets` (..., rounds), `m` (..., rounds) one candidate mean per round."""
    rounds = x.shape[-2]
    with np.errstate(divide="ignore"):  # m = 0: no truncation is needed, the bet's losses are bounded by x >= 0
        bet = np.minimum(bets[..., None, :], TRUNCATION / m[..., :, None])  # (..., r, s)
    gains = np.log1p(bet[..., None] * (x[..., None, :, :] - m[..., :, None, None])).sum(axis=-1)
    return np.where(np.tri(rounds, dtype=bool), gains, 0.0).sum(axis=-1)


def _lower_ends(x: np.ndarray, bets: np.ndarray, alpha: float, weight: float) -> np.ndarray:
    """Per round, the least m at which weight K+(m) is below 1/alpha (a non-increasing function of m)."""
    threshold = np.log(1.0 / alpha) - np.log(weight)
    shape = x.shape[:-1]
    excluded, included = np.zeros(shape), np.ones(shape)  # weight K+(1) <= weight < 1/alpha: 1 is always inside
    zero_inside = _log_capital_above(x, bets, excluded) < threshold
    for _ in range(BISECTION_STEPS):
        middle = (excluded + included) / 2.0
        inside = _log_capital_above(x, bets, middle) < threshold
        included, excluded = np.where(inside, middle, included), np.where(inside, excluded, middle)
    # The last excluded candidate: outwards by at most 2^-34.
    return np.where(zero_inside, 0.0, excluded)


def mean_sequence(x: np.ndarray, alpha: float) -> tuple[np.ndarray, np.ndarray]:
    """The hedged-capital confidence sequence (low, high) after each round for the task-averaged mean of `x`
    (..., rounds, tasks) in [0, 1], as running intersections, each of shape (..., rounds)."""
    x = np.asarray(x, dtype=float)
    if x.size and (x.min() < 0.0 or x.max() > 1.0):
        raise ValueError("a confidence sequence by betting needs observations in [0, 1]")
    bets = np.sqrt(2.0 * np.log(2.0 / alpha)) * plug_in_bets(x)
    low = _lower_ends(x, bets, alpha, HEDGE)
    # K- against m on x is K+ against 1 - m on 1 - x, whose plug-in bets are the same.
    high = 1.0 - _lower_ends(1.0 - x, bets, alpha, 1.0 - HEDGE)
    return np.maximum.accumulate(low, axis=-1), np.minimum.accumulate(high, axis=-1)


def rate_interval(outcomes: np.ndarray, alpha: float) -> AnytimeInterval:
    """A cell's success rate (%) over the rounds of `outcomes` (round, task) in {0, 1}, with its confidence
    sequence at the last of them."""
    low, high = mean_sequence(outcomes, alpha)
    return AnytimeInterval(100.0 * float(np.mean(outcomes)), 100.0 * float(low[-1]), 100.0 * float(high[-1]), len(outcomes))


def contrast_interval(differences: np.ndarray, alpha: float) -> AnytimeInterval:
    """A - B (pp) over the rounds of the paired `differences` (round, task) in [-1, 1], with the confidence
    sequence at the last of them: the sequence for the mean of (a - b + 1) / 2, mapped back to 2 m - 1."""
    low, high = mean_sequence((np.asarray(differences, dtype=float) + 1.0) / 2.0, alpha)
    return AnytimeInterval(100.0 * float(np.mean(differences)), 100.0 * float(2.0 * low[-1] - 1.0),
                           100.0 * float(2.0 * high[-1] - 1.0), len(differences))
