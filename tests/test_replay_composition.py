"""Composition statistics on hand-built error vectors, and analysis.json assembly from replays."""

import json
import math

import numpy as np
import pytest

from vlaquantbench.errors import UserError
from vlaquantbench.replay import composition as C
from vlaquantbench.replay.analysis import Roles, analyze, analyze_files
from vlaquantbench.replay.run import ReplayRun
from paths import REFERENCE



def rows(*vectors):
    return np.array(vectors, dtype=float)


def test_additive_errors_ratio_at_most_one_residual_zero_cosine_one():
    e_a = rows([1.0, 2.0, 0.0], [0.0, 1.0, 0.0])
    e_b = rows([3.0, -1.0, 2.0], [0.0, 2.0, 0.0])
    e_u = e_a + e_b
    ratio = C.norm_ratio(e_u, e_a, e_b)
    assert np.all(ratio <= 1.0 + 1e-12)
    assert ratio[1] == pytest.approx(1.0)  # parallel errors: triangle inequality is tight
    assert C.norm_ratio_to_sum(e_u, e_a, e_b) == pytest.approx([1.0, 1.0])
    assert C.residual(e_u, e_a, e_b) == pytest.approx([0.0, 0.0], abs=1e-12)
    assert C.cosine(e_u, e_a, e_b) == pytest.approx([1.0, 1.0])


def test_orthogonal_equal_errors_give_ratio_one_over_sqrt_two():
    e_a, e_b = rows([2.0, 0.0]), rows([0.0, 2.0])
    assert C.norm_ratio(e_a + e_b, e_a, e_b) == pytest.approx([1 / math.sqrt(2)])


def test_cancelling_errors_ratio_below_one_and_union_larger_than_sum():
    # A and B cancel (e_A = -e_B): addition predicts ~0 error, but the union errs like A alone.
    e_a, e_b = rows([1.0, 0.0]), rows([-0.9, 0.0])
    additive = e_a + e_b
    assert C.norm_ratio(additive, e_a, e_b) == pytest.approx([0.1 / 1.9])
    e_u = rows([1.0, 0.0])
    assert C.norm_ratio_to_sum(e_u, e_a, e_b) == pytest.approx([10.0])
    assert C.residual(e_u, e_a, e_b) == pytest.approx([0.9])
    assert C.cosine(e_u, e_a, e_b) == pytest.approx([1.0])


def test_interaction_orthogonal_to_sum_gives_zero_cosine_and_ratio_above_one():
    e_a, e_b = rows([1.0, 0.0, 0.0]), rows([0.0, 1.0, 0.0])
    e_u = rows([0.0, 0.0, 5.0])
    assert C.cosine(e_u, e_a, e_b) == pytest.approx([0.0])
    assert C.norm_ratio(e_u, e_a, e_b) == pytest.approx([2.5])
    assert C.residual(e_u, e_a, e_b) == pytest.approx([math.sqrt(27) / 5])


def test_error_vectors_flatten_chunks_and_reject_misaligned_shapes():
    ref = np.zeros((2, 50, 7))
    chunks = ref.copy()
    chunks[1, 3, 6] = 0.5
    e = C.error_vectors(chunks, ref)
    assert e.shape == (2, 350) and e[1].sum() == 0.5
    assert C.chunk_mae(chunks, ref) == pytest.approx([0.0, 0.5 / 350])
    with pytest.raises(ValueError, match="differ in shape"):
        C.error_vectors(chunks[:, :10], ref)


def test_median_iqr_and_share_lower():
    assert C.median_iqr([1, 2, 3, 4, 5]) == {"median": 3.0, "iqr": [2.0, 4.0]}
    assert C.share_lower([0.1, 0.5, 0.2, 0.3], than=[0.2, 0.4, 0.2, 0.4]) == pytest.approx(0.5)


def test_executed_action_errors_pool_calls_and_keep_sign():
    ref = np.zeros((4, 2))
    actions = np.array([[0.1, -0.2], [0.1, 0.2], [0.1, -0.2], [0.1, -0.2]])
    out = C.executed_action_errors(actions, ref)
    assert out["executed_action_mae_per_dim"] == pytest.approx([0.1, 0.2])
    assert out["executed_action_signed_mean_per_dim"] == pytest.approx([0.1, -0.1])
    assert out["executed_action_mae"] == pytest.approx(0.15)


def test_flow_state_deviation_per_denoising_step():
    ref = np.zeros((3, 10, 50, 32))
    states = ref.copy()
    states[:, 9] += 0.25  # only the state entering the tenth update differs
    dev = C.flow_state_deviation(states, ref)
    assert len(dev) == 10 and dev[:9] == [0.0] * 9 and dev[9] == pytest.approx(0.25)


def test_activation_input_stats_token_absmax_and_abs_kurtosis():
    x = np.array([[1.0, -2.0], [0.5, 0.5], [-4.0, 0.0], [1.0, 1.0]])
    stats = dict(zip(C.DOWNPROJ_COLUMNS, C.activation_input_stats(x)))
    assert stats["tok_absmax_mean"] == pytest.approx(np.mean([2.0, 0.5, 4.0, 1.0]))
    assert stats["tok_absmax_max"] == 4.0 and stats["n_tokens"] == 4
    a = np.abs(x).ravel()
    assert stats["abs_kurtosis"] == pytest.approx(np.mean((a - a.mean()) ** 4) / np.var(a) ** 2)
    # Averaged per call within a trajectory, then over trajectories and layers.
    traj1 = np.stack([np.full((2, 6), 1.0), np.full((2, 6), 3.0)])  # 2 calls, 2 layers
    traj2 = np.full((1, 2, 6), 10.0)
    assert C.average_call_stats([traj1, traj2]) == pytest.approx(np.full(6, 6.0))


def _run(name, layers, chunks_by_record, actions_by_record, recorded):
    records, arrays = [], {}
    for rec, chunks in chunks_by_record.items():
        actions = actions_by_record[rec]
        arrays[rec] = {
            "chunks": chunks,
            "actions": actions,
            "flow_states": np.repeat(chunks[:, None], 10, axis=1) * np.linspace(0, 1, 10)[None, :, None, None],
            "downproj": np.full((len(chunks), 2, 6), float(layers)),
        }
        records.append({"record": rec, "n_steps": len(actions), "n_chunks": len(chunks),
                        "dev_from_recorded_actions": float(np.abs(actions - recorded[rec]).mean())})
    return ReplayRun({"config": name, "preset": "W4A4" if layers else "BASELINE", "quantized_layers": layers,
                      "records": records}, arrays)


def _study_runs():
    rng = np.random.default_rng(0)
    recs = {"t0_e20.npz": 3, "t1_e20.npz": 2}
    base = {r: rng.normal(size=(n, 5, 7)) for r, n in recs.items()}
    recorded = {r: rng.normal(size=(n * 2, 7)) for r, n in recs.items()}
    e_a = {r: rng.normal(size=c.shape) * 0.1 for r, c in base.items()}
    e_b = {r: rng.normal(size=c.shape) * 0.1 for r, c in base.items()}
    def make(name, layers, err, act_shift):
        return _run(name, layers, {r: base[r] + err[r] for r in recs},
                    {r: recorded[r] + act_shift for r in recs}, recorded)
    zero = {r: np.zeros_like(c) for r, c in base.items()}
    return [
        make("baseline", 0, zero, 0.0),
        make("baseline2", 0, zero, 0.0),
        make("attention", 72, e_a, 0.01),
        make("adarms", 36, e_b, -0.02),
        make("union", 108, {r: e_a[r] + e_b[r] for r in recs}, 0.03),  # exactly additive
        make("s126", 126, {r: 2 * e_a[r] for r in recs}, 0.05),
        make("s167", 167, {r: e_a[r] for r in recs}, 0.04),
    ]


def test_analyze_matches_authors_layout_and_statistics(tmp_path):
    runs = _study_runs()
    result = analyze(runs, Roles())
    authors = json.loads(
        (REFERENCE / "authors-files/results/replay/pi05_spatial/W4A4/analysis.json").read_text()
    )
    assert set(result) == set(authors)
    assert set(result["configs"]["union"]) == set(authors["configs"]["union"])
    assert set(result["additivity"]) == set(authors["additivity"])
    assert set(result["recovery"]) == set(authors["recovery"])
    add = result["additivity"]
    assert add["n_chunks"] == 5
    assert add["residual_over_union"]["median"] == pytest.approx(0.0, abs=1e-12)
    assert add["cosine_union_vs_sum"]["median"] == pytest.approx(1.0)
    assert add["norm_union_over_sum_of_norms"]["median"] <= 1.0
    rec = result["recovery"]
    assert rec["chunk_mae_167"] == pytest.approx(rec["chunk_mae_126"] / 2)
    assert rec["frac_chunks_167_lower"] == 1.0
    assert result["repeatability_floor"] == 0.0
    union = result["configs"]["union"]
    assert union["executed_action_signed_mean_per_dim"] == pytest.approx([0.03] * 7)
    assert union["dev_from_recorded_actions"] == pytest.approx(0.03)
    assert union["flow_step_divergence"][0] == 0.0
    assert result["configs"]["s167"]["downproj_tok_absmax_p99"] == pytest.approx(167.0)
    # Files on disk round-trip through analyze_files.
    paths = [r.save(tmp_path / "W4A4" / f"{r.name}.json") for r in runs]
    out = analyze_files(paths, tmp_path / "W4A4" / "analysis.json")
    assert out["additivity"] == add
    assert json.loads((tmp_path / "W4A4" / "analysis.json").read_text())["recovery"] == rec


def test_analyze_names_missing_configuration_and_mismatched_trajectories():
    runs = _study_runs()
    with pytest.raises(UserError, match="'union'"):
        analyze([r for r in runs if r.name != "union"])
    runs[3].summary["records"] = runs[3].summary["records"][:1]
    with pytest.raises(UserError, match="adarms"):
        analyze(runs)


def test_nonzero_repeatability_floor_is_reported():
    runs = _study_runs()
    runs[1].arrays["t0_e20.npz"]["actions"] = runs[1].arrays["t0_e20.npz"]["actions"] + 1e-3
    assert analyze(runs)["repeatability_floor"] == pytest.approx(1e-3)
