"""Record -> replay (one job per configuration) -> analyze -> tables on the demo pi0.5 policy in
real LIBERO, through Snakemake."""

import json
import subprocess
import sys

import numpy as np
import pytest

from vlaquantbench.replay.run import ReplayRun
from vlaquantbench.replay.study import analysis_files
from vlaquantbench.replay.tables import write_replay_table
from file_audit import audited_env, job_audits, undeclared
from paths import ROOT

STUDY = "results/replay/pi05_libero_spatial"
TARGETS = ["tables/replay_composition.tex", "tables/replay_bias.tex", "figures/replay_formats.pdf",
           "results/diagnostics/pi05-ah-W4A4.json"]


@pytest.fixture(scope="module")
def demo_dag(tmp_path_factory):
    work = tmp_path_factory.mktemp("replay_dag")
    for item in ("Snakefile", "rules", "workflow", "config", "src", "manifests"):
        if (ROOT / item).exists():
            (work / item).symlink_to(ROOT / item)
    cmd = [sys.executable, "-m", "snakemake", *TARGETS, "--cores", "2", "--configfile", "config/replay_demo.yaml"]
    proc = subprocess.run(cmd, cwd=work, capture_output=True, text=True, timeout=1800,
                          env=audited_env(work.parent / f"{work.name}-audit"))
    assert proc.returncode == 0, proc.stderr[-4000:]
    return work


@pytest.mark.slow
def test_replay_jobs_touch_exactly_their_declared_files(demo_dag):
    audit = demo_dag.parent / f"{demo_dag.name}-audit"
    assert {job["rule"] for job in job_audits(audit)} == {
        "replay_record", "replay_configuration", "replay_analyze", "replay_composition_table", "replay_bias_table",
        "replay_formats_figure", "diagnostics_collect"}
    assert undeclared(audit, demo_dag) == {}


@pytest.mark.slow
def test_recording_stores_what_the_policy_saw_and_did(demo_dag):
    meta = json.loads((demo_dag / STUDY / "records/records.json").read_text())
    assert [r["record"] for r in meta["records"]] == ["t0_e20.npz", "t0_e21.npz"]
    assert meta["chunk"] == {"predicted": 50, "executed": 10}
    assert meta["versions"]["mujoco"] == "3.3.2" and meta["code_revision"]
    with np.load(demo_dag / STUDY / "records/t0_e20.npz") as rec:
        calls = len(rec["chunk"])
        assert calls == 1 and rec["executed"].tolist() == [10]  # 10 steps at 10 executed per call
        assert rec["agentview"].shape[0] == rec["wrist"].shape[0] == rec["state"].shape[0] == calls
        assert rec["agentview"].dtype == np.uint8 and rec["state"].shape[1] == 8
        assert rec["chunk"].shape == (calls, 50, 7) and rec["flow_states"].shape[:2] == (calls, 10)
        assert rec["actions"].shape == (10, 7) and int(rec["seed"]) == 20
        assert str(rec["instruction"])
        assert rec["rng_state"].shape[0] == calls


@pytest.mark.slow
def test_full_precision_replays_reproduce_the_recording_exactly(demo_dag):
    for name in ("baseline", "baseline2"):
        run = ReplayRun.load(demo_dag / STUDY / "fp" / f"{name}.json")
        assert [r["dev_from_recorded_actions"] for r in run.summary["records"]] == [0.0, 0.0]
        assert run.summary["quantized_layers"] == 0
    analysis = json.loads((demo_dag / STUDY / "W4A4/analysis.json").read_text())
    assert analysis["repeatability_floor"] == 0.0
    assert analysis["configs"]["baseline2"]["chunk_mae_mean"] == 0.0


@pytest.mark.slow
def test_quantized_replays_use_checked_layer_counts_and_fired_hooks(demo_dag):
    expected = {"attention": 72, "adarms": 36, "union": 108, "s126": 126, "s167": 167}
    for name, layers in expected.items():
        run = ReplayRun.load(demo_dag / STUDY / "W4A4" / f"{name}.json")
        assert run.summary["quantized_layers"] == layers
        assert run.summary["hooks"]["selected"] == run.summary["hooks"]["fired"] == layers
        assert run.summary["quant_report"]["ah"]["layers"] == layers
        assert len(run.summary["downproj_layers"]) == 18
        assert all(r["dev_from_recorded_actions"] > 0 for r in run.summary["records"])
    analysis = json.loads((demo_dag / STUDY / "W4A4/analysis.json").read_text())
    assert analysis["additivity"]["n_chunks"] == 2
    assert analysis["configs"]["s167"]["chunk_mae_mean"] > 0
    assert len(analysis["configs"]["union"]["flow_step_divergence"]) == 10
    assert analysis["configs"]["union"]["flow_step_divergence"][0] == 0.0  # shared initial noise


@pytest.mark.slow
def test_tables_render_from_the_demo_analysis(demo_dag):
    composition = (demo_dag / "tables/replay_composition.tex").read_text()
    analysis = json.loads((demo_dag / STUDY / "W4A4/analysis.json").read_text())
    ratio = analysis["additivity"]["norm_union_over_sum_of_norms"]["median"]
    assert f"W4A4 & {ratio:.2f} & " in composition
    assert (demo_dag / "tables/replay_bias.tex").read_text().count(r" \\") == 6  # header + 5 scopes
    assert (demo_dag / "figures/replay_formats.pdf").read_bytes().startswith(b"%PDF")
    all_formats = write_replay_table("all_formats", analysis_files(demo_dag / STUDY, ["W4A4"]), demo_dag / "all.tex",
                                     study=ROOT / "config/replay/pi05_libero_spatial.yaml", formats=["W4A4"])
    assert r"W4A4 & Attention & 72 & -- & " in all_formats


@pytest.mark.slow
def test_diagnostics_collected_on_the_recording_with_provenance(demo_dag):
    from vlaquantbench.diagnostics.files import Diagnostics
    from vlaquantbench.quant import get_subset

    diag = Diagnostics.read(demo_dag / "results/diagnostics/pi05-ah-W4A4.json")
    assert len(diag.layers) == 167 and diag.header["preset"] == "W4A4"
    prov = diag.header["provenance"]
    assert prov["init_states"] == [20, 21] and prov["tasks"] == [0] and prov["seed"] == 0
    assert prov["mujoco"] == "3.3.2" and prov["torch"] and prov["vqb_commit"]
    assert all(layer["calls"] == 2 * 10 for layer in diag.layers.values())  # 2 calls x 10 flow steps
    # The closed-loop subsets select the same layers from the collected names.
    for subset in ("onlyself_attn", "attn_adarms", "down_attn_adarms"):
        s = get_subset("pi05", subset)
        assert len(diag.select(s.only, s.exclude)) == s.layers
