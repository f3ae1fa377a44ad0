"""A study cell of a checkpoint trained here (`study.models.<model>.trained`): the DAG resolves the checkpoint
and revision from its training.json, runs the cell on Meta-World through the real rollout rule, loading the
checkpoint and its tokenizer offline from its own HF_HOME folder, and the header names what ran. A bad entry
is refused while the DAG is built, naming the field."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest
import yaml

from paths import ROOT
from vlaquantbench.cells import cell_config
from vlaquantbench.errors import UserError
from vlaquantbench.records import read_cell
from vlaquantbench.runner.provenance import host

HOME = "checkpoints/pi05_metaworld_cpu"  # the committed CPU-trained pi0.5 (config/trained_cpu.yaml)
GPU_HOME = "checkpoints/pi05_metaworld"  # the committed GPU-trained pi0.5 (config/trained_study.yaml)
TRAINING = json.loads((ROOT / HOME / "training.json").read_text())
REF = "metaworld/metaworld_mt50/pi05/rtn-W4A4-ah"


def study(**weights) -> dict:
    return {"models": {"pi05": {"variant": "full", "trained": HOME, **weights}}, "tasks": [18], "episodes_per_task": 1,
            "runner": {"max_steps": 10}}


def workflow_with_tables(tmp_path):
    """A checkout linking the workflow, the package and the committed checkpoint (its outputs its own), and an
    empty folder for a test's table definitions."""
    checkout = tmp_path / "checkout"
    checkout.mkdir()
    for item in ("Snakefile", "rules", "workflow", "config", "src", "checkpoints"):
        (checkout / item).symlink_to(ROOT / item)
    tables = tmp_path / "tables"
    tables.mkdir()
    return checkout, tables


def test_the_cell_config_pins_the_trained_checkpoint_and_its_input():
    cfg = cell_config(REF, study())
    assert (cfg["checkpoint"], cfg["revision"]) == (TRAINING["checkpoint"], TRAINING["revision"])
    # The executed chunk the policy was trained with and its 64-pixel input, hashed with the cell.
    assert cfg["runner"]["executed_chunk"] == TRAINING["policy"]["n_action_steps"] == 5
    assert cfg["runner"]["camera_size"] == 64


@pytest.mark.parametrize("change, message", [
    ({"trained": "checkpoints/nowhere"}, "study.models.pi05.trained: checkpoints/nowhere: no training.json: train the checkpoint first"),
    ({"checkpoint": "lerobot/pi05_base"}, "study.models.pi05.trained: the checkpoint and revision come from its training.json"),
    ({"variant": "demo"}, "study.models.pi05.trained: a trained checkpoint runs as variant full, not 'demo'"),
])
def test_a_bad_trained_entry_is_refused_naming_the_field(change, message):
    with pytest.raises(UserError, match=message):
        cell_config(REF, study(**change))


def test_layer_errors_give_every_quantized_cell_calibration_rows():
    """`study.calibration.layer_errors`: an RTN cell, which needs no statistics to quantize, samples the
    calibration's input rows (for its header's `mean_rel_mse`); BASELINE runs none; smoothing cells keep theirs."""
    errors = {**study(), "calibration": {"layer_errors": True}}
    assert cell_config(REF, study())["calibration"] is None
    assert cell_config(REF, errors)["calibration"]["sample_rows"] == 128
    assert cell_config(REF.replace("rtn-W4A4-ah", "rtn-BASELINE-e2e"), errors)["calibration"] is None
    smoothing = cell_config(REF.replace("rtn-W4A4-ah", "calib-W4A4-ah"), errors)["calibration"]
    assert smoothing == cell_config(REF.replace("rtn-W4A4-ah", "calib-W4A4-ah"), study())["calibration"]
    assert "sample_rows" not in smoothing


def test_a_checkpoint_of_another_model_is_refused():
    raw = {"models": {"pi0": {"variant": "full", "trained": HOME}}, "tasks": [18], "episodes_per_task": 1}
    with pytest.raises(UserError, match=f"study.models.pi0.trained: {HOME} holds a 'pi05' checkpoint "
                                        rf"\({TRAINING['checkpoint']}@{TRAINING['revision']}\), not a 'pi0' one"):
        cell_config("metaworld/metaworld_mt50/pi0/rtn-BASELINE-e2e", raw)


@pytest.mark.slow
def test_the_dag_runs_a_trained_checkpoint_cell_and_its_header_names_the_revision(tmp_path):
    """`snakemake tables/<t>.tex` with one W4A4 action-head row on the trained policy: one 10-step episode of
    drawer-close. The checkpoint is in no HF_HOME of the process: the jobs load it from the entry's folder."""
    checkout, tables = workflow_with_tables(tmp_path)
    (tables / "trained.yaml").write_text(yaml.safe_dump({
        "caption": "trained", "align": "lrr", "header": [["Cell", "Episodes", "Jerk"]],
        "values": [{"stat": "episodes", "cell": "cell"}, {"stat": "mean_ci", "cell": "cell", "field": "jerk"}],
        "rows": [{"label": "W4A4 AH", "cell": REF}]}))
    config = tmp_path / "trained.yaml"
    # layer_errors: the RTN cell's calibration samples input rows (one 10-step episode from variation 400).
    calibration = {"layer_errors": True, "tasks": [18], "first_init_state": 400, "episodes": 1}
    config.write_text(yaml.safe_dump({
        "tables": ["trained"], "tables_dir": str(tables),
        "study": {**study(checkpoint=None, revision=None), "calibration": calibration,
                  "execution": {"num_envs": 1, "progress": False}}}))
    env = {k: v for k, v in os.environ.items() if k not in ("HF_HOME", "HF_HUB_CACHE")}
    env["HF_HOME"] = str(tmp_path / "empty_hf_home")  # nothing there: the trained folder must be used
    result = subprocess.run([sys.executable, "-m", "snakemake", "--cores", "2", "tables/trained.tex",
                             f"--configfile={config}"], cwd=checkout, capture_output=True, text=True, timeout=300, env=env)
    assert result.returncode == 0, result.stderr[-3000:]
    cell = read_cell(next((checkout / "results" / "cells").iterdir()))
    assert (cell.header["checkpoint"], cell.header["revision"]) == (TRAINING["checkpoint"], TRAINING["revision"])
    assert cell.header["tokenizer"]["repo"] == TRAINING["tokenizer"]["repo"]
    assert cell.header["normalization"]["policy_postprocessor"]["norm_map"]["ACTION"] == "MEAN_STD"
    assert len(cell.episodes) == 1 and cell.episodes["task_name"].tolist() == ["drawer-close-v3"]
    assert cell.header["host"] == host()  # the CPU and renderer the episodes ran on
    # The action head's error on the sampled calibration rows, measured through the layers' input hooks.
    assert 0 < cell.header["quant_report"]["ah"]["mean_rel_mse"] < 1
    assert cell.header["quant_report"]["act_calib"] and "smoothing" not in cell.header["quant_format"]
    assert "W4A4 AH & 1 & " in (checkout / "tables" / "trained.tex").read_text()


def test_vqb_rollout_runs_a_trained_checkpoint_cell_from_its_folder_into_the_dags_cell_folder(tmp_path):
    """`vqb rollout` of a full-precision cell on the trained policy (one 10-step episode of drawer-close), offline
    with an empty HF_HOME: the stamp names the trained folder, as the DAG's checkpoint job writes it (before,
    the command asked the hub for the checkpoint), and the cell lands in the folder the DAG would use."""
    from vlaquantbench.cells import checkpoint_key, config_hash
    from vlaquantbench.config.study import StudyConfig
    from vlaquantbench.workflow import CELLS_DIR

    ref = "metaworld/metaworld_mt50/pi05/rtn-BASELINE-e2e"
    entry = study(checkpoint=None, revision=None)
    config = tmp_path / "trained.yaml"
    config.write_text(yaml.safe_dump({"study": {**entry, "execution": {"num_envs": 1, "progress": False}}}))
    env = {k: v for k, v in os.environ.items() if k not in ("HF_HOME", "HF_HUB_CACHE")}
    env.update(HF_HOME=str(tmp_path / "empty_hf_home"), HF_HUB_OFFLINE="1")  # nothing to fetch from
    result = subprocess.run([sys.executable, "-m", "vlaquantbench.cli", "rollout", ref, "--config", str(config),
                             "--results", str(tmp_path)], cwd=ROOT, capture_output=True, text=True, timeout=300, env=env)
    assert result.returncode == 0, result.stderr[-3000:]
    cfg = cell_config(ref, StudyConfig.from_dict(entry))
    stamp = json.loads((tmp_path / "results" / "checkpoints" / checkpoint_key(cfg) / "checkpoint.json").read_text())
    assert stamp["trained_home"] == str((ROOT / HOME).absolute()) and stamp["revision"] == TRAINING["revision"]
    cell = read_cell(tmp_path / CELLS_DIR / config_hash(cfg))
    assert (cell.header["checkpoint"], cell.header["revision"]) == (TRAINING["checkpoint"], TRAINING["revision"])
    assert len(cell.episodes) == 1 and cell.episodes["task_name"].tolist() == ["drawer-close-v3"]


def test_the_header_stat_prints_a_components_error_from_the_committed_records():
    """tables/methods_2026's MSE columns on the committed records: each method's action-head error (RTN's too: the
    study sets `layer_errors`), `--` for a component outside the scope; a header without the field at all is an
    error naming it."""
    from vlaquantbench.tables.definition import TableDefinition
    from vlaquantbench.tables.latex import render_latex

    base = "metaworld/metaworld_mt50/pi05/"
    cells = {base + name: read_cell(ROOT / "results/methods_2026" / base / name) for name in ("gptq-W4A4-ah", "rtn-W4A4-ah")}
    expected = {name: cells[base + name].header["quant_report"]["ah"]["mean_rel_mse"] for name in ("gptq-W4A4-ah", "rtn-W4A4-ah")}
    raw = {"caption": "mse", "align": "lrr", "header": [["Cell", "VE", "AH"]],
           "values": [{"stat": "header", "cell": "cell", "key": "quant_report.ve.mean_rel_mse"},
                      {"stat": "header", "cell": "cell", "key": "quant_report.ah.mean_rel_mse"}],
           "rows": [{"label": "gptq", "cell": base + "gptq-W4A4-ah"}, {"label": "rtn", "cell": base + "rtn-W4A4-ah"}]}
    latex = render_latex(TableDefinition.from_dict("mse", raw), cells)
    assert f"gptq & -- & {expected['gptq-W4A4-ah']:.1e} \\\\" in latex and f"rtn & -- & {expected['rtn-W4A4-ah']:.1e} \\\\" in latex
    assert expected["gptq-W4A4-ah"] < expected["rtn-W4A4-ah"]  # GPTQ's rounding lowers the layers' output error
    raw["values"][0]["key"] = "quant_reprot.ve.mean_rel_mse"
    with pytest.raises(UserError, match=f"cell {base}gptq-W4A4-ah: its header .* has no quant_reprot"):
        render_latex(TableDefinition.from_dict("mse", raw), cells)


@pytest.mark.slow
def test_the_trained_policy_shows_a_real_quantization_effect(tmp_path):
    """A real effect, through `snakemake` on the GPU-trained checkpoint (config/trained_study.yaml) in real
    Meta-World: full precision succeeds on every episode of coffee-button and drawer-close (variations 0-4,
    never demonstrated; 20 of 20 each in its closed-loop check, benchmarks/results/gpu_train_policy/), RTN W2A2
    over the whole policy on far fewer of the same episodes. Random weights would fail the first assertion:
    they never succeed."""
    checkout, tables = workflow_with_tables(tmp_path)
    base = "metaworld/metaworld_mt50/pi05/"
    (tables / "effect.yaml").write_text(yaml.safe_dump({
        "caption": "effect", "align": "lr", "header": [["Cell", "Success"]], "values": [{"stat": "rate", "cell": "cell"}],
        "rows": [{"label": "FP", "cell": base + "rtn-BASELINE-e2e"}, {"label": "W2A2", "cell": base + "rtn-W2A2-e2e"}]}))
    config = tmp_path / "effect.yaml"
    # Five simulator workers a cell: a task's five episodes run as one batch, and the policy acts on five
    # observations a call (W2A2's ten 150-step episodes in two rounds; fewer, larger calls than batches of two,
    # for the same episodes: the runner's records do not depend on the batch).
    config.write_text(yaml.safe_dump({
        "tables": ["effect"], "tables_dir": str(tables),
        "study": {"models": {"pi05": {"variant": "full", "trained": GPU_HOME, "checkpoint": None, "revision": None}},
                  "tasks": [8, 18], "episodes_per_task": 5, "runner": {"max_steps": 150},
                  "execution": {"num_envs": 5, "torch_threads": 1, "progress": False}}}))
    # One thread per rollout: the two cells run side by side (the full-precision one is short).
    result = subprocess.run([sys.executable, "-m", "snakemake", "--cores", "2", "tables/effect.tex", f"--configfile={config}",
                             "--set-threads", "rollout=1"], cwd=checkout, capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, result.stderr[-3000:]
    cells = {read_cell(folder).header["cell"]: read_cell(folder).episodes for folder in (checkout / "results" / "cells").iterdir()}
    full, w2a2 = cells["rtn-BASELINE-e2e"], cells["rtn-W2A2-e2e"]
    key = ["task_id", "episode", "seed"]
    assert sorted(map(tuple, full[key].to_numpy())) == sorted(map(tuple, w2a2[key].to_numpy()))  # the same episodes
    per_task = full.groupby("task_name")["success"].sum()
    assert (per_task == 5).all() and len(per_task) == 2, per_task  # all of 5, on both tasks
    # 50 points or more: the drop no reading of chance explains
    assert w2a2["success"].sum() <= full["success"].sum() - 5, (w2a2["success"].sum(), full["success"].sum())
