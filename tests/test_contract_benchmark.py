"""The seam's contract (issue 50): a third benchmark that lives only under tests/ (`tests/contract_benchmark/`: a
MuJoCo scene it writes itself, a suite, a worker vector env, a declaration that registers itself) runs a cell
through the real Snakemake workflow, records and a table included, and a same-observation replay records and
replays it, with no file under src/ naming it. Processes
find it through `VQB_BENCHMARKS` (`envs.registry`), the one hook a package outside `envs/` needs.

The policy is the `metaworld_expert` model: the scene's `environment_state` has Meta-World's observation layout,
so Meta-World's scripted reach experts drive it (no network, BASELINE cells only). Nothing is registered in this
test process: every check that needs the benchmark runs in a subprocess, so other tests see two benchmarks."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pandas as pd
import pytest
import yaml

from paths import ROOT

TESTS = ROOT / "tests"
REF = "contract/contract_reach/metaworld_expert/rtn-BASELINE-e2e"
STUDY = {"models": {"metaworld_expert": {"variant": "full"}}, "tasks": 2, "episodes_per_task": 3,
         "runner": {"max_steps": None}}


def contract_env() -> dict[str, str]:
    """The environment every process of a run inherits: tests/ importable, the declaration module named."""
    return {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT / "src"), str(TESTS)]),
            "VQB_BENCHMARKS": "contract_benchmark.benchmark"}


def python(code: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=contract_env(),
                          cwd=ROOT, timeout=300)


def test_no_file_under_src_names_the_contract_benchmark():
    named = subprocess.run(["git", "grep", "-n", "-i", "contract_benchmark\\|contract_reach", "--", "src"],
                           cwd=ROOT, capture_output=True, text=True)
    assert named.returncode == 1 and not named.stdout, named.stdout


def test_the_contract_benchmark_registers_itself_and_its_cells_are_checked_while_the_dag_is_built():
    run = python(
        "from vlaquantbench.envs import BENCHMARK_SUITES\n"
        "from vlaquantbench.cells import cell_config\n"
        "from vlaquantbench.errors import UserError\n"
        f"study = {STUDY!r}\n"
        "print(sorted(BENCHMARK_SUITES), BENCHMARK_SUITES['contract']['contract_reach'].tasks)\n"
        f"cfg = cell_config({REF!r}, study)\n"
        "print(cfg['benchmark'], cfg['suite'], cfg['runner']['max_steps'])\n"
        "for bad in ({'settle_steps': 3}, {'max_steps': 61}):\n"
        f"    try: cell_config({REF!r}, {{**study, 'runner': bad}})\n"
        "    except UserError as err: print(err)\n"
        f"try: cell_config({REF!r}, {{**study, 'episodes_per_task': 6}})\n"
        "except UserError as err: print(err)\n")
    assert run.returncode == 0, run.stderr[-3000:]
    lines = run.stdout.splitlines()
    assert lines[0] == "['contract', 'libero', 'metaworld'] 2"
    assert lines[1] == "contract contract_reach 40"  # the benchmark's own step limit, resolved into the cell
    assert lines[2] == (f"cell {REF!r}: study.runner.settle_steps: 'settle_steps' is not an env setting of contract "
                        "(it takes camera_size, mujoco, success_radius; settle_steps is libero's); remove it, or set it "
                        "under study.models.<model>.runner for the models whose cells run on libero only")
    assert lines[3].startswith(f"cell {REF!r}: study.runner.max_steps: 61 steps is beyond contract_reach's limit of "
                               "60 env steps an episode (the contract scene's worker: it refuses to step on)")
    assert lines[4].startswith(f"cell {REF!r}: study.episodes_per_task: 6 episodes per task, but contract_reach has 5")


# A setting of the contract benchmark's own (`ContractSettings.success_radius`), which no runner option names and
# nothing under src/ knows: set from a config file, checked against its declaration, hashed with the cell, and
# passed to its worker. A radius of 0.3 m holds every goal placement (each within 0.235 m of the hand's start), so a
# zero action succeeds at once; at the declared 0.05 m it does not.
SETTING = """
import sys
import numpy as np
from contract_benchmark.suite import ContractSuite
from vlaquantbench.cells import CellConfig, config_hash
from vlaquantbench.config import load_workflow_config
from vlaquantbench.config.study import StudyConfig
from vlaquantbench.envs import env_settings, make_env
from vlaquantbench.errors import UserError

ref = sys.argv[2]
study = StudyConfig.from_dict(load_workflow_config(sys.argv[1])["study"])
cell = CellConfig.from_ref(ref, study)
default = CellConfig.from_ref(ref, StudyConfig.from_dict({**load_workflow_config(sys.argv[1])["study"], "runner": {}}))
print(cell.to_dict()["runner"]["success_radius"], default.to_dict()["runner"]["success_radius"],
      cell.config_hash != default.config_hash, CellConfig.from_dict(cell.to_dict()) == cell)
suite = ContractSuite("contract_reach")
spec = suite.episode_spec(0, 0)
print(round(float(np.linalg.norm(np.subtract(suite.task_variation(spec), (0.0, 0.0, 0.3)))), 3))
for settings in (cell.env, default.env):
    with make_env("contract", suite, 1, **env_settings(settings, reads_images=False)) as env:
        env.reset([spec])
        _, success = env.step(np.zeros((1, 4)))
        print(env.success_radius, success[0])
for bad in ("far", 0):
    try:
        CellConfig.from_ref(ref, StudyConfig.from_dict({"models": {"metaworld_expert": {"variant": "full"}},
                                                        "runner": {"success_radius": bad}}))
    except UserError as err:
        print(err)
"""


def test_a_setting_only_the_contract_benchmark_declares_is_set_from_a_config_and_reaches_its_env_and_hash(tmp_path):
    config = tmp_path / "contract.yaml"
    config.write_text(yaml.safe_dump({"tables": [], "study": {**STUDY, "runner": {"max_steps": None,
                                                                                  "success_radius": 0.3}}}))
    run = subprocess.run([sys.executable, "-c", SETTING, str(config), REF], capture_output=True, text=True,
                         env=contract_env(), cwd=ROOT, timeout=300)
    assert run.returncode == 0, run.stderr[-3000:]
    lines = run.stdout.splitlines()
    assert lines[0] == "0.3 0.05 True True"  # in the canonical runner, and so in the hash; read back as it was
    assert float(lines[1]) > 0.05  # the first episode's goal lies beyond the declared radius
    assert lines[2:4] == ["0.3 True", "0.05 False"]  # the worker judges success by the cell's radius
    assert lines[4] == (f"cell {REF!r}: study.runner.success_radius: 'far' is not of type 'number' (contract's env "
                        "setting success_radius: {'type': ['number'], 'exclusiveMinimum': 0})")
    assert lines[5].startswith(f"cell {REF!r}: study.runner.success_radius: 0 is less than or equal to the minimum of 0")


@pytest.mark.slow
def test_a_contract_cell_runs_through_snakemake_into_records_and_a_table(tmp_path):
    checkout = tmp_path / "checkout"
    checkout.mkdir()
    for item in ("Snakefile", "rules", "workflow", "manifests", "config", "src"):
        (checkout / item).symlink_to(ROOT / item)
    tables = tmp_path / "tables"
    tables.mkdir()
    (tables / "contract.yaml").write_text(yaml.safe_dump({
        "caption": "Scripted reach experts on the contract scene ({episodes}; {steps}).", "align": "lrr",
        "header": [["Task", "Episodes", "SR"]], "cells": {"experts": REF},
        "values": [{"stat": "episodes", "cell": "experts"}, {"stat": "rate_ci", "cell": "experts"}],
        "rows": [{"label": "reach", "task": "reach-v3"}, {"label": "reach-wall", "task": "reach-wall-v3"},
                 {"midrule": True}, {"label": "all tasks"}]}))
    config = {"tables": ["contract"], "tables_dir": str(tables),
              "study": {**STUDY, "label": "contract", "execution": {"num_envs": 2, "torch_threads": 1}}}
    (tmp_path / "contract.yaml").write_text(yaml.safe_dump(config))
    result = subprocess.run([sys.executable, "-m", "snakemake", "--cores", "2", "tables/contract.tex",
                             "tables/summary.csv", f"--configfile={tmp_path / 'contract.yaml'}"],
                            cwd=checkout, capture_output=True, text=True, timeout=600, env=contract_env())
    assert result.returncode == 0, result.stderr[-3000:]

    # records: one cell folder, its header naming the benchmark and the simulator, every episode in the protocol
    [folder] = (checkout / "results" / "cells").iterdir()
    header = json.loads((folder / "header.json").read_text())
    assert (header["benchmark"], header["suite"], header["config"]["ref"]) == ("contract", "contract_reach", REF)
    assert header["versions"]["mujoco"] == header["versions"]["mujoco_pinned"] and header["max_steps"] == 40
    # the records pass the schema its header bounds, each placement checked against the suite's own draw
    checked = python(f"from vlaquantbench.records import read_cell; cell = read_cell({str(folder)!r}); "
                     "print(cell.n_episodes, cell.n_successes)")
    assert checked.returncode == 0 and checked.stdout.split() == ["6", "6"], checked.stderr[-3000:]
    episodes = pd.read_parquet(folder / "episodes.parquet")
    assert sorted(zip(episodes["task_id"], episodes["episode"])) == [(t, e) for t in (0, 1) for e in range(3)]
    assert episodes["seed"].tolist() == [1009 * t + e for t, e in zip(episodes["task_id"], episodes["episode"])]
    assert set(episodes["task_name"]) == {"reach-v3", "reach-wall-v3"}
    # the experts reach every goal, each placement the one its seeded variation draws (the record check)
    assert episodes["success"].all() and episodes["steps"].between(5, 40).all(), episodes[["success", "steps"]]
    assert len({tuple(v) for v in episodes["task_variation"]}) == 6
    # a table and the summary read the cell's records
    table = (checkout / "tables" / "contract.tex").read_text()
    assert "reach & 3 & 100.0" in table and "reach-wall & 3 & 100.0" in table and "all tasks & 6 & 100.0" in table
    summary = pd.read_csv(checkout / "tables" / "summary.csv")
    assert summary[["benchmark", "suite", "model", "episodes"]].values.tolist() == [
        ["contract", "contract_reach", "metaworld_expert", 6]]


# Replay records any benchmark from its declared cameras: the pi0.5 policy trained here on Meta-World reads the
# contract scene's observations (its `main` camera under a key of its own, `overhead`, found by role; a 4-dim
# state, 4-dim actions).
REPLAY = '''
import json, sys
from pathlib import Path
import numpy as np
from vlaquantbench.diagnostics.collect import collect
from vlaquantbench.replay.configuration import replay_configuration
from vlaquantbench.replay.record import record
from vlaquantbench.replay.study import RecordSettings
from vlaquantbench.models.trained_home import policy_folder

root, folder = Path(sys.argv[1]), Path(sys.argv[2])
home = root / "checkpoints" / "pi05_metaworld_cpu"
training = json.loads((home / "training.json").read_text())
snapshot = str(policy_folder(home))  # a plain checkpoint folder (docs/checkpoints.md)
layers = json.loads((root / "results/methods_2026/metaworld/metaworld_mt50/pi05/rtn-W4A4-ah/header.json")
                    .read_text())["quant_report"]["ah"]["layers"]
settings = RecordSettings(model="pi05", variant="full", suite="contract_reach", benchmark="contract", tasks=[1],
                          init_states=[2], observe=["paligemma_with_expert.gemma_expert.model.layers.*.mlp.down_proj"],
                          checkpoint=training["checkpoint"], revision=training["revision"], checkpoint_dir=snapshot,
                          max_steps=10, executed_chunk=training["policy"]["n_action_steps"])
trajectories = [folder / name for name in settings.trajectory_files()]
out = {}
meta = record(settings, folder / "records.json", trajectories)
with np.load(trajectories[0]) as data:
    out["files"] = sorted(data.files)
    out["image"], out["state"] = list(data["overhead"].shape), list(data["state"].shape)
    recorded = data["chunk"]
out["benchmark"], out["n_steps"] = meta["benchmark"], meta["records"][0]["n_steps"]
def replay(preset, n):
    study = {"model": "pi05", "configurations": {"head": {"scope": "ah", "subset": None, "layers": n}}}
    return replay_configuration(folder / "records.json", trajectories, study, "head", preset, snapshot)
baseline = replay("BASELINE", 0)
out["baseline_dev"] = baseline.summary["records"][0]["dev_from_recorded_actions"]
out["baseline_exact"] = bool(np.array_equal(baseline.stacked("chunks"), recorded))
quantized = replay("W4A4", layers)
out["hooks"] = [layers, quantized.summary["hooks"]["selected"], quantized.summary["hooks"]["fired"]]
out["quantized_dev"] = quantized.summary["records"][0]["dev_from_recorded_actions"]
diagnostics = collect(folder / "records.json", trajectories, "pi05", "ah", "W4A4", folder / "diag.json", snapshot)
out["diagnosed_layers"], out["diagnosed_tasks"] = len(diagnostics["layers"]), diagnostics["provenance"]["tasks"]
print("RESULT " + json.dumps(out))
'''


@pytest.mark.slow
def test_replay_records_the_contract_benchmark_and_reproduces_it(tmp_path):
    """Same-observation, same-noise replay on the contract scene: the recording holds its declared camera and the
    state, a full-precision replay reproduces the recorded chunks exactly, a quantized replay of the action head
    fires every selected hook and changes them, and the layer diagnostics run on the recording."""
    run = subprocess.run([sys.executable, "-c", REPLAY, str(ROOT), str(tmp_path)], capture_output=True, text=True,
                         env=contract_env(), cwd=ROOT, timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
    [line] = [line for line in run.stdout.splitlines() if line.startswith("RESULT ")]
    out = json.loads(line.removeprefix("RESULT "))
    assert out["benchmark"] == "contract" and out["n_steps"] == 10
    assert {"overhead", "state"} <= set(out["files"]) and not {"agentview", "image"} & set(out["files"])
    assert out["image"][1:] == [48, 48, 3] and out["state"][1:] == [4] and out["image"][0] == out["state"][0]
    assert out["baseline_dev"] == 0.0 and out["baseline_exact"]
    layers, selected, fired = out["hooks"]
    assert layers > 0 and selected == fired == layers and out["quantized_dev"] > 0
    assert out["diagnosed_layers"] == layers and out["diagnosed_tasks"] == [1]
