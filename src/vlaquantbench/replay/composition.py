"""Same-observation replay statistics as pure array functions (paper App. `app:pi05_replay`).

Every function takes arrays already aligned call by call: chunk `j` of configuration Q and
chunk `j` of full precision were predicted from the same observation with the same flow noise,
so their difference is the numerical effect of quantization alone.
"""

from __future__ import annotations

import numpy as np


def error_vectors(chunks: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """e_{Q,j} = vec(c_{Q,j} - c_{FP,j}): one flattened row per chunk, shape [n_chunks, horizon*dims]."""
    chunks, reference = np.asarray(chunks, np.float64), np.asarray(reference, np.float64)
    if chunks.shape != reference.shape:
        raise ValueError(f"chunk arrays differ in shape: {chunks.shape} vs {reference.shape}")
    return (chunks - reference).reshape(len(chunks), -1)


def _norms(e: np.ndarray) -> np.ndarray:
    return np.linalg.norm(e, axis=1)


def norm_ratio(e_union: np.ndarray, e_a: np.ndarray, e_b: np.ndarray) -> np.ndarray:
    """‖e_A∪B‖ / (‖e_A‖ + ‖e_B‖) per chunk; at most 1 when e_A∪B = e_A + e_B (triangle inequality)."""
    return _norms(e_union) / (_norms(e_a) + _norms(e_b))


def norm_ratio_to_sum(e_union: np.ndarray, e_a: np.ndarray, e_b: np.ndarray) -> np.ndarray:
    """‖e_A∪B‖ / ‖e_A + e_B‖ per chunk; exactly 1 under vector addition."""
    return _norms(e_union) / _norms(e_a + e_b)


def residual(e_union: np.ndarray, e_a: np.ndarray, e_b: np.ndarray) -> np.ndarray:
    """‖e_A∪B − e_A − e_B‖ / ‖e_A∪B‖ per chunk; 0 under vector addition."""
    return _norms(e_union - e_a - e_b) / _norms(e_union)


def cosine(e_union: np.ndarray, e_a: np.ndarray, e_b: np.ndarray) -> np.ndarray:
    """cos(e_A∪B, e_A + e_B) per chunk; 1 under vector addition."""
    total = e_a + e_b
    return np.einsum("ij,ij->i", e_union, total) / (_norms(e_union) * _norms(total))


def median_iqr(values: np.ndarray) -> dict:
    """Median and interquartile range (numpy's linear-interpolation quantiles)."""
    q25, q50, q75 = np.percentile(np.asarray(values, np.float64), [25, 50, 75])
    return {"median": float(q50), "iqr": [float(q25), float(q75)]}


def chunk_mae(chunks: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Mean absolute coordinate error within each full chunk, one value per chunk."""
    return np.abs(error_vectors(chunks, reference)).mean(axis=1)


def share_lower(errors: np.ndarray, than: np.ndarray) -> float:
    """Share of chunks on which `errors` is strictly below `than` (e.g. 167 layers vs 126)."""
    errors, than = np.asarray(errors), np.asarray(than)
    if errors.shape != than.shape:
        raise ValueError(f"per-chunk errors differ in shape: {errors.shape} vs {than.shape}")
    return float(np.mean(errors < than))


def executed_action_errors(actions: np.ndarray, reference: np.ndarray) -> dict:
    """Executed-action MAE (all coordinates, and per coordinate) and signed bias per coordinate.

    Rows are control calls pooled over trajectories, cached actions included, so longer
    trajectories weigh more. Signed bias is quantized minus full precision.
    """
    diff = np.asarray(actions, np.float64) - np.asarray(reference, np.float64)
    return {
        "executed_action_mae": float(np.abs(diff).mean()),
        "executed_action_mae_per_dim": np.abs(diff).mean(axis=0).tolist(),
        "executed_action_signed_mean_per_dim": diff.mean(axis=0).tolist(),
    }


def flow_state_deviation(states: np.ndarray, reference: np.ndarray) -> list[float]:
    """Mean |x_t^Q − x_t^FP| of the state entering each denoising step, states [n_chunks, steps, ...].

    Entry 0 is the shared initial noise (0 by construction); the last entry precedes the final
    update, so it differs from the final chunk MAE.
    """
    states, reference = np.asarray(states, np.float64), np.asarray(reference, np.float64)
    if states.shape != reference.shape:
        raise ValueError(f"flow-state arrays differ in shape: {states.shape} vs {reference.shape}")
    diff = np.abs(states - reference)
    return diff.reshape(diff.shape[0], diff.shape[1], -1).mean(axis=(0, 2)).tolist()


DOWNPROJ_COLUMNS = ("tok_absmax_mean", "tok_absmax_p50", "tok_absmax_p99", "tok_absmax_max", "abs_kurtosis", "n_tokens")


def activation_input_stats(x: np.ndarray) -> np.ndarray:
    """One call's input statistics for a layer, x [..., features], in DOWNPROJ_COLUMNS order.

    Token-wise absmax is what a per-token activation quantizer scales by; the kurtosis is the
    fourth standardized moment of |x| over all values (not of the signed activations).
    """
    x = np.asarray(x, np.float64).reshape(-1, np.shape(x)[-1])
    tok_absmax = np.abs(x).max(axis=1)
    a = np.abs(x).ravel()
    centered = a - a.mean()
    var = np.mean(centered**2)
    kurt = float(np.mean(centered**4) / var**2) if var > 0 else float("nan")
    p50, p99 = np.percentile(tok_absmax, [50, 99])
    return np.array([tok_absmax.mean(), p50, p99, tok_absmax.max(), kurt, len(tok_absmax)])


def average_call_stats(per_trajectory: list[np.ndarray]) -> np.ndarray:
    """Average per-call statistics [calls, layers, columns] within each trajectory, then over
    trajectories and layers: one value per column."""
    return np.mean([np.asarray(t, np.float64).mean(axis=0) for t in per_trajectory], axis=(0, 1))
