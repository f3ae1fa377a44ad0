"""The study on the GPU-trained pi0.5, prepared on a machine without a GPU: config/gpu_study.yaml holds the cells
chosen for it (the baseline in full, every quantized cell under the live stopping rule against it),
config/gpu_study_fixed.yaml the five cells rerun in full, and `snakemake -n` plans exactly those rollouts (the
workflow states its NO_GPU refusal and plans all the same). benchmarks/gpu_study.sh runs the study across device
calls: a cell stopped by its graceful deadline in one call, its records carried as the call's tar parts into a
fresh checkout and resumed there, equals the same cell run at once, episode by episode.

What is proven elsewhere and not repeated: a rollout stopped by SIGTERM resumes to the uninterrupted records
(tests/test_runner_interrupt.py, LIBERO, one task), kill -9 at any point loses and duplicates nothing
(tests/test_runner_soak.py), and a sequential cell resumed from a truncated journal decides the same
(tests/test_runner_stopping.py). Here: Meta-World, the trained checkpoint, two tasks interleaved under the live
rule, and the device script's own stop, pack, restore and resume through Snakemake."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest
import yaml

from paths import ROOT
from vlaquantbench.config import _merge, _parse, validate
from vlaquantbench.records import read_cell
from vlaquantbench.runner.journal import TIMING_FIELDS, journal_episodes
from vlaquantbench.workflow import WorkflowConfig

LIVE, FIXED, KERNELS = "config/gpu_study.yaml", "config/gpu_study_fixed.yaml", "config/gpu_kernels.yaml"
SCRIPT = ROOT / "benchmarks" / "gpu_study.sh"
BASE = "metaworld/metaworld_mt50/pi05/"
BASELINE = BASE + "rtn-BASELINE-e2e"
TRAINED = yaml.safe_load((ROOT / "config" / "trained_study.yaml").read_text())
FIVE = ["rtn-W2A2-e2e", "rtn-W2-e2e", "rtn-W8A8-e2e", "rtn-W8-e2e", "rtn-W4A4-e2e"]  # chosen before the study


def study_cells(*configs: str) -> dict[str, dict]:
    """The cells (config hash -> canonical config) `snakemake --configfile CONFIGS` runs, as the DAG builds them."""
    raw = _parse(ROOT / "config" / "config.yaml")
    for config in configs:
        raw = _merge(raw, _parse(ROOT / config))
    return WorkflowConfig.from_snakemake(validate(raw, "config", " ".join(configs)), ROOT).study_cells()


def expected_live_cells() -> set[str]:
    presets, scopes = ["W8", "W4", "W3", "W2", "W8A8", "W4A8", "W4A4"], ["e2e", "ve", "llm", "ah"]
    subsets = ["onlyself_attn", "onlyadarms", "attn_adarms", "only_gate", "only_up", "only_down", "onlymlp",
               "mlp_plus_adarms", "down_attn", "down_attn_adarms", "noadarms", "only_action_out", "no_action_out"]
    names = {"rtn-BASELINE-e2e", "rtn-W2A2-e2e", "rtn-FP8E4M3-e2e", "rtn-MXFP4-e2e"}
    names |= {f"rtn-{p}-{s}" for p in presets for s in scopes}
    names |= {f"ablate-W4A4-ah-{s}" for s in subsets}
    names |= {f"{m}-{p}-{s}" for m in ("gptq", "hadamard", "hadamard_gptq") for p in ("W4A8", "W4A4") for s in ("e2e", "ah")}
    return {BASE + name for name in names}


def test_the_study_runs_the_chosen_cells_on_the_same_episodes_each_quantized_one_under_the_live_rule():
    cells = study_cells(LIVE)
    assert {cfg["ref"] for cfg in cells.values()} == expected_live_cells() and len(cells) == 57
    baseline = next(key for key, cfg in cells.items() if cfg["ref"] == BASELINE)
    assert "sequential" not in cells[baseline]  # the cell tested against runs its 200 episodes in full
    for key, cfg in cells.items():
        assert cfg["tasks"] == sorted([4, 6, 8, 15, 13, 19, 18, 24, 48, 49]) and cfg["episodes_per_task"] == 20
        assert cfg["seed"] == 0 and cfg["runner"]["device"] == "cuda" and cfg["runner"]["max_steps"] == 150
        # The camera and the executed chunk come from the checkpoint (what its training section fixed).
        assert cfg["runner"]["camera_size"] == TRAINED["demonstrations"]["image_size"]
        assert cfg["runner"]["executed_chunk"] == TRAINED["training"]["policy"]["n_action_steps"]
        if key != baseline:
            assert cfg["sequential"] == {"alpha": 0.05, "margin_pp": 5, "against": {"ref": BASELINE, "config_hash": baseline}}
            assert cfg["calibration"]["sample_rows"] == 128  # each component's error in every quantized header


def test_the_fixed_overlay_reruns_the_five_cells_chosen_before_the_study_in_full():
    live = {cfg["ref"]: key for key, cfg in study_cells(LIVE).items()}
    fixed = {cfg["ref"]: (key, cfg) for key, cfg in study_cells(LIVE, FIXED).items()}
    assert set(fixed) == {BASELINE, *(BASE + name for name in FIVE)}
    assert fixed[BASELINE][0] == live[BASELINE]  # one baseline, run once
    for name in FIVE:
        key, cfg = fixed[BASE + name]
        assert "sequential" not in cfg and cfg["episodes_per_task"] == 20
        assert key != live[BASE + name]  # its own folder beside the live cell's


def dry_run(tmp_path: Path, *configs: str, targets: tuple[str, ...] = ()) -> str:
    """`snakemake -n` of CONFIGS in a checkout linking the workflow and the committed checkpoints: its output."""
    checkout = tmp_path / "checkout"
    checkout.mkdir()
    for item in ("Snakefile", "rules", "workflow", "config", "src", "checkpoints"):
        (checkout / item).symlink_to(ROOT / item)
    args = ["--configfile", *configs]  # one flag: Snakemake 9 keeps only the last of several --configfile flags
    env = {k: v for k, v in os.environ.items() if k != "CUDA_VISIBLE_DEVICES"}
    result = subprocess.run([sys.executable, "-m", "snakemake", "-n", *targets, "--cores", "16", *args], cwd=checkout,
                            capture_output=True, text=True, timeout=300, env=env)
    assert result.returncode == 0, result.stderr[-3000:]
    return result.stdout + result.stderr


def planned(output: str, rule: str) -> list[dict[str, str]]:
    """The jobs of `rule` in a dry run's output: each block's input and output lines."""
    blocks = re.split(r"\n(?=\[[^\]]+\]\nrule |rule )", output)
    jobs = []
    for block in blocks:
        if re.match(rf"(\[[^\]]+\]\n)?rule {rule}:", block):
            fields = dict(re.findall(r"^\s+(input|output): (.*)$", block, re.MULTILINE))
            jobs.append(fields)
    return jobs


def job_count(output: str, rule: str) -> int:
    return int(re.search(rf"^{rule}\s+(\d+)$", output, re.MULTILINE)[1])


def test_a_dry_run_plans_the_studys_rollouts_each_quantized_one_after_the_baseline(tmp_path):
    cells = study_cells(LIVE)
    output = dry_run(tmp_path, LIVE)
    if shutil.which("nvidia-smi") is None:
        assert "a real run stops here (a dry run plans the jobs all the same)" in output
    assert job_count(output, "rollout") == 57 and job_count(output, "calibrate") == 6
    rollouts = planned(output, "rollout")
    planned_cells = {re.search(r"results/cells/(\w+)/", job["output"])[1]: job["input"] for job in rollouts}
    assert set(planned_cells) == set(cells)
    baseline = next(key for key, cfg in cells.items() if cfg["ref"] == BASELINE)
    for key, inputs in planned_cells.items():  # a sequential cell reads the baseline's records: it waits for them
        assert (f"results/cells/{baseline}/episodes.parquet" in inputs) == (key != baseline), cells[key]["ref"]


def test_a_dry_run_of_the_fixed_overlay_plans_its_six_cells_and_the_rules_replay_on_them(tmp_path):
    output = dry_run(tmp_path, LIVE, FIXED, targets=("tables/gpu_fixed.tex", "tables/sequential.tex"))
    assert job_count(output, "rollout") == 6 and job_count(output, "sequential_table") == 1
    for job in planned(output, "rollout"):  # no stopping rule: no cell waits for the baseline's records
        assert "results/cells/" not in job["input"]


def test_the_study_stack_packs_the_ten_tasks_of_the_study():
    """benchmarks/simstack.py packs a study config's Meta-World tasks (their meshes and textures) from its task ids."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        from simstack import metaworld_tasks
    finally:
        sys.path.remove(str(ROOT / "benchmarks"))
    assert metaworld_tasks(ROOT / LIVE) == TRAINED["demonstrations"]["tasks"]


def test_the_device_call_the_script_documents_fits_the_device_tool():
    """Its header's `run(...)`: a command of at most 2,000 characters, at most 8 carried paths, both git-ignored."""
    header = SCRIPT.read_text().split("\nset -u", 1)[0]
    call = re.search(r"run\((.*?)\)\n", header.replace("\n#      ", " "), re.DOTALL)[1]
    command = re.search(r'command="([^"]*)"', call)[1]
    carry = re.findall(r'"([^"]+)"', re.search(r"carry=\[([^\]]*)\]", call)[1])
    assert len(command) <= 2000 and 1 <= len(carry) <= 8
    ignored = subprocess.run(["git", "check-ignore", *carry], cwd=ROOT, capture_output=True, text=True).stdout.split()
    assert ignored == carry
    assert subprocess.run(["bash", "-n", str(SCRIPT)]).returncode == 0


def test_a_cell_finished_in_an_earlier_call_is_no_target_though_its_records_are_not_carried(tmp_path):
    """The carry holds the baseline's records and the unfinished cells' journals; every other finished cell is known
    from the carried progress alone, and `plan` (what the next call runs) counts it finished."""
    checkout = tmp_path / "checkout"
    checkout.mkdir()
    for item in ("Snakefile", "rules", "workflow", "config", "src", "checkpoints", "benchmarks"):
        (checkout / item).symlink_to(ROOT / item)
    cells = study_cells(LIVE)
    done = next(key for key, cfg in cells.items() if cfg["ref"] == BASE + "rtn-W2-e2e")
    (checkout / "results").mkdir()
    (checkout / "results" / "gpu_study_progress.tsv").write_text(
        "hash\tref\tpreset\tsequential\tepisodes\tfinished\tdecision\n"
        f"{done}\t{BASE}rtn-W2-e2e\tW2\t1\t30\t1\tworse\n")
    result = subprocess.run(["bash", str(SCRIPT), "plan"], cwd=checkout, capture_output=True, text=True, check=True,
                            env={**os.environ, "PYTHON": sys.executable, "PHASES": LIVE})
    flags = dict(line.split()[::2] for line in result.stdout.splitlines()[1:])
    assert len(flags) == 57 and flags.pop(done) == "1" and set(flags.values()) == {"0"}


def test_an_unfinished_cell_recorded_on_another_host_is_set_aside_and_one_of_this_host_stays(tmp_path):
    """A journal resumes only on its host's CPU and renderer (runner.journal): the call restarts such a cell, its
    journal kept in results/cells_set_aside/ (returned with the records) rather than refused mid-call."""
    from vlaquantbench.runner.provenance import host

    checkout = tmp_path / "checkout"
    checkout.mkdir()
    for item in ("src", "benchmarks", "config"):
        (checkout / item).symlink_to(ROOT / item)
    for name, recorded in (("elsewhere", {**host(), "cpu": "another CPU"}), ("here", host())):
        (checkout / "results" / "cells" / name).mkdir(parents=True)
        (checkout / "results" / "cells" / name / "journal.jsonl").write_text(
            json.dumps({"kind": "header", "ref": BASE + name, "host": recorded}) + "\n")
    result = subprocess.run(["bash", str(SCRIPT), "check-hosts"], cwd=checkout, capture_output=True, text=True,
                            env={**os.environ, "PYTHON": sys.executable}, check=True)
    assert result.stdout.startswith(f"set aside elsewhere ({BASE}elsewhere): recorded on ")
    assert [p.name for p in (checkout / "results" / "cells").iterdir()] == ["here"]
    assert [p.name.split("-")[0] for p in (checkout / "results" / "cells_set_aside").iterdir()] == ["elsewhere"]


# --- the script across two calls, on the CPU -----------------------------------------------------------------------
# The committed CPU-trained pi0.5 on two of its tasks, two variations each, one simulator worker (episodes finish one
# by one, so the stop lands between them), RTN W4A4 end to end under the live rule against the baseline.
SMALL_STUDY = {
    "tables": ["small"],
    "study": {
        "models": {"pi05": {"variant": "full", "trained": "checkpoints/pi05_metaworld_cpu", "checkpoint": None,
                            "revision": None}},
        "tasks": [4, 18], "episodes_per_task": 2, "seed": 0,
        "runner": {"device": "cpu", "max_steps": 15, "flow_steps": 2, "sampler": "eager"},
        "calibration": {"layer_errors": False},
        "sequential": {"alpha": 0.05, "margin_pp": 5, "against": "rtn-BASELINE-e2e"},
        "execution": {"num_envs": 1, "torch_threads": 1, "progress": False, "episode_order": "interleaved"},
    },
}
CELL = BASE + "rtn-W4A4-e2e"


def small_checkout(tmp_path: Path, name: str) -> Path:
    """A checkout (workflow, package, checkpoints and benchmarks linked) with the small study's config and table."""
    checkout = tmp_path / name
    checkout.mkdir()
    for item in ("Snakefile", "rules", "workflow", "config", "src", "checkpoints", "benchmarks"):
        (checkout / item).symlink_to(ROOT / item)
    tables = checkout / "small_tables"
    tables.mkdir()
    (tables / "small.yaml").write_text(yaml.safe_dump({
        "caption": "small", "align": "lr", "header": [["Cell", "Episodes"]], "values": [{"stat": "episodes", "cell": "cell"}],
        "rows": [{"label": "FP", "cell": BASELINE}, {"label": "W4A4", "cell": CELL}]}))
    config = {**SMALL_STUDY, "tables_dir": str(tables)}
    (checkout / "small.yaml").write_text(yaml.safe_dump({**config, "study": {**config["study"], "tables_dir": str(tables)}}))
    return checkout


def script(checkout: Path, out: Path, **env) -> subprocess.Popen:
    out.mkdir()
    variables = {**os.environ, "OUT": str(out), "PYTHON": sys.executable, "PHASES": "small.yaml", "CORES": "2",
                 "STACK": str(checkout / "no_stack"), "STUDY_END_S": "1500", **env}
    return subprocess.Popen(["bash", str(SCRIPT)], cwd=checkout, env=variables, start_new_session=True,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def keep(checkout: Path, out: Path) -> None:
    """`gpu_study.sh keep`: a call's returned files, kept here as the next call's carry and the records."""
    subprocess.run(["bash", str(SCRIPT), "keep", str(out)], cwd=checkout, check=True, capture_output=True)


def finished(process: subprocess.Popen, timeout: float = 900) -> str:
    try:
        output, _ = process.communicate(timeout=timeout)
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()
    assert process.returncode == 0, output[-3000:]
    return output


def cell_folder(checkout: Path, ref: str) -> Path | None:
    """The cell's folder: its header names it, or while it runs, its journal's first line."""
    for folder in (checkout / "results" / "cells").glob("*"):
        for name in ("header.json", "journal.jsonl"):
            if (folder / name).is_file():
                try:  # a journal's header line may be half written
                    text = (folder / name).open().readline() if name == "journal.jsonl" else (folder / name).read_text()
                    if json.loads(text)["ref"] == ref:
                        return folder
                except ValueError:
                    pass
                break
    return None


def outcomes(folder: Path) -> pd.DataFrame:
    episodes = read_cell(folder).episodes
    return episodes.drop(columns=[c for c in TIMING_FIELDS if c in episodes]).sort_values(["task_id", "episode"]).reset_index(drop=True)


@pytest.mark.slow
def test_a_cell_stopped_in_one_call_and_resumed_from_its_carried_records_equals_the_cell_run_at_once(tmp_path):
    # At once: the baseline and the cell in one call.
    whole = small_checkout(tmp_path, "whole")
    finished(script(whole, tmp_path / "whole_out"))
    at_once = cell_folder(whole, CELL)
    assert len(read_cell(at_once).episodes) == 4

    # Call 1: stopped (the stop file, as the deadline stops it) once the cell has journaled an episode.
    first = small_checkout(tmp_path, "first")
    stop = tmp_path / "stop"
    call = script(first, tmp_path / "first_out", STOP_FILE=str(stop))
    deadline = time.monotonic() + 900
    while not ((folder := cell_folder(first, CELL)) and journal_episodes(folder / "journal.jsonl")):
        assert call.poll() is None and time.monotonic() < deadline, "the cell journaled no episode"
        time.sleep(0.2)
    stop.touch()
    output = finished(call)
    assert "stopping the rollouts (stop file): SIGTERM" in output
    done_first = journal_episodes(cell_folder(first, CELL) / "journal.jsonl")
    assert 1 <= len(done_first) < 4 and not (cell_folder(first, CELL) / "episodes.parquet").exists()
    parts = sorted((tmp_path / "first_out").glob("records.tgz.part*"))
    assert parts and all(part.stat().st_size <= 15_000_000 for part in parts)
    progress = pd.read_csv(tmp_path / "first_out" / "progress.tsv", sep="\t").set_index("ref")
    assert progress.at[CELL, "episodes"] == len(done_first) and progress.at[CELL, "finished"] == 0
    assert progress.at[BASELINE, "finished"] == 1

    # Call 2, a fresh checkout: the first call's carry kept as the next call's .carry/gpu_study, the cell resumed.
    second = small_checkout(tmp_path, "second")
    keep(second, tmp_path / "first_out")
    output = finished(script(second, tmp_path / "second_out"))
    resumed = cell_folder(second, CELL)
    # The baseline carried in finished is not rerun (its records are the first call's, byte for byte) ...
    baseline_first, baseline_second = (cell_folder(c, BASELINE) / "episodes.parquet" for c in (first, second))
    assert baseline_second.read_bytes() == baseline_first.read_bytes()
    assert not (second / "logs" / "rollout" / f"{baseline_second.parent.name}.log").exists()
    # ... the cell kept the first call's episodes and ran only the rest ...
    assert journal_episodes(resumed / "journal.jsonl")[: len(done_first)] == done_first
    # ... and its records are the ones of the cell run at once, episode by episode, with the same stop.
    pd.testing.assert_frame_equal(outcomes(resumed), outcomes(at_once))
    assert read_cell(resumed).header["stopping"] == read_cell(at_once).header["stopping"]
    calls = pd.read_csv(tmp_path / "second_out" / "calls.tsv", sep="\t")
    assert len(calls) == 2 and calls["episodes"].sum() == 8 and calls["total_episodes"].iloc[-1] == 8

    # Here, every call's returned records exported to the layout to commit: each finished cell by reference.
    here = small_checkout(tmp_path, "here")
    for out in ("first_out", "second_out"):
        keep(here, tmp_path / out)
    subprocess.run(["bash", str(SCRIPT), "export"], cwd=here, env={**os.environ, "PYTHON": sys.executable}, check=True)
    for kind, ref in (("live", BASELINE), ("live", CELL), ("fixed", BASELINE)):
        pd.testing.assert_frame_equal(outcomes(here / "results" / "gpu_study" / kind / ref), outcomes(cell_folder(second, ref)))
    assert not (here / "results" / "gpu_study" / "fixed" / CELL).exists()


# --- the study saved between sessions ------------------------------------------------------------------------------
SAVED = ROOT / "results" / "gpu_study"


def test_the_committed_carry_resumes_the_study_its_finished_cells_committed_as_records(tmp_path):
    """`save` committed the carry and the finished cells; `resume` puts the carry back, and what it restores is the
    study's phases (config/gpu_study.yaml, then its fixed reruns and the real-kernel cells of config/gpu_kernels.yaml):
    its finished cells are the committed records (same hashes, same episodes) and its unfinished ones are journals of
    the phases' cells. A second `resume` over a carry is refused."""
    env = {**os.environ, "PYTHON": sys.executable, "CARRY": str(tmp_path / "carry"), "SAVED": str(SAVED / "carry")}
    resumed = subprocess.run(["bash", str(SCRIPT), "resume"], cwd=ROOT, env=env, capture_output=True, text=True)
    assert resumed.returncode == 0, resumed.stderr
    again = subprocess.run(["bash", str(SCRIPT), "resume"], cwd=ROOT, env=env, capture_output=True, text=True)
    assert again.returncode == 1 and "already holds a carry" in again.stderr
    subprocess.run(["tar", "-xzf", str(tmp_path / "carry" / "carry.tgz")], cwd=tmp_path, check=True)
    progress = pd.read_csv(tmp_path / "results" / "gpu_study_progress.tsv", sep="\t")
    phases = study_cells(LIVE) | study_cells(LIVE, FIXED) | study_cells(LIVE, KERNELS)
    assert set(progress["hash"]) <= set(phases) and progress["hash"].is_unique
    committed = {cell.header["config_hash"]: cell for cell in map(read_cell, SAVED.glob("*/*/*/*/*"))}
    finished = progress[progress["finished"] == 1]
    assert set(finished["hash"]) == set(committed) and len(committed) > 1
    for row in finished.itertuples():
        assert committed[row.hash].header["ref"] == row.ref and len(committed[row.hash].episodes) == row.episodes
    baseline = committed[progress.loc[progress["preset"] == "BASELINE", "hash"].item()]
    assert (tmp_path / "results" / "cells" / baseline.header["config_hash"] / "episodes.parquet").is_file()
    for row in progress[progress["finished"] == 0].itertuples():  # carried as journals, to be resumed
        journal = tmp_path / "results" / "cells" / row.hash / "journal.jsonl"
        assert len(journal_episodes(journal)) == row.episodes > 0
