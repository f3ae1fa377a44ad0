"""The precision search on the GPU-trained pi0.5, prepared on a machine without a GPU: config/gpu_search.yaml holds
the GPU study's policy, tasks and runner with the search's space (components x {W8A8, W4A8, W4A4, W4, W3, W2} by
RTN) under the search's own live rule; `snakemake -n` plans its cells with rule rollout's priorities in the search's
order (cheapest weight memory first), so that a run cut short by its device calls has decided the cheap candidates;
benchmarks/gpu_search.sh decides on the device, from the finished cells' decisions, when the search is determined
and what the confirmation then runs. What the search answers from a part of its space (a run cut short) is tested
in tests/test_search.py; the device script's carry and resume in tests/test_gpu_study.py."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml
from test_gpu_study import dry_run, job_count, planned, study_cells

from paths import ROOT
from vlaquantbench.cells import cell_config, config_hash
from vlaquantbench.config import _merge, _parse, load_workflow_config, validate
from vlaquantbench.config.study import StudyConfig
from vlaquantbench.search import Candidate, SearchDesign, check_live_design, search_order
from vlaquantbench.sequential import stopping_rule
from vlaquantbench.tables import load_table

SEARCH, BASE_PHASE, CONFIRM = "config/gpu_search.yaml", "config/gpu_search_baseline.yaml", "config/gpu_search_confirm.yaml"
SCRIPT = ROOT / "benchmarks" / "gpu_search.sh"
GROUP = "metaworld/metaworld_mt50/pi05"
BASELINE = f"{GROUP}/rtn-BASELINE-e2e"
SCOPES = ("ve", "llm", "ah", "ve_mp_llm", "e2e")
FORMATS = ("W8A8", "W4A8", "W4A4", "W4", "W3", "W2")
CANDIDATES = [f"{GROUP}/rtn-{preset}-{scope}" for scope in SCOPES for preset in FORMATS]
GPU_BASELINE = ROOT / "results/gpu_study/live" / GROUP / "rtn-BASELINE-e2e"  # the GPU study's, 200 episodes


def merged(*configs: str) -> dict:
    """The config `snakemake --configfile CONFIGS` runs with (each file merged over the last, over config/config.yaml)."""
    raw = _parse(ROOT / "config" / "config.yaml")
    for config in configs:
        raw = _merge(raw, _parse(ROOT / config))
    return validate(raw, "config", " ".join(configs))


def by_ref(cells: dict[str, dict]) -> dict[str, tuple[str, dict]]:
    return {cfg["ref"]: (key, cfg) for key, cfg in cells.items()}


def test_the_space_is_components_by_formats_on_the_gpu_studys_policy_under_the_searchs_rule():
    cells = by_ref(study_cells(SEARCH))
    assert sorted(cells) == sorted([BASELINE, *CANDIDATES])
    study = by_ref(study_cells("config/gpu_study.yaml"))
    _, reference = study[BASELINE]  # the GPU study's baseline: its policy, tasks and runner
    raw = load_workflow_config(ROOT / SEARCH)
    design = SearchDesign(raw["search"]["alpha"], raw["search"]["margin_pp"])
    assert (design.alpha, design.margin_pp, raw["search"]["allocation"]) == (0.05, 5, "gpu_search")
    live = StudyConfig.from_dict(raw["study"]).sequential
    check_live_design(design, len(CANDIDATES), BASELINE, live.alpha, live.margin_pp, live.against)  # no refusal
    assert live.alpha == pytest.approx(0.05 / 30, rel=1e-15)
    baseline_key = cells[BASELINE][0]
    for ref, (key, cfg) in cells.items():
        for field in ("checkpoint", "revision", "tasks", "runner", "seed", "benchmark", "suite"):
            assert cfg[field] == reference[field], (ref, field)
        assert cfg["episodes_per_task"] == 50 and cfg["calibration"] is None  # RTN, no layer errors
        if ref == BASELINE:
            assert "sequential" not in cfg  # the cell tested against runs its 500 episodes in full
        else:
            assert cfg["sequential"] == {"alpha": live.alpha, "margin_pp": 5,
                                         "against": {"ref": BASELINE, "config_hash": baseline_key}}
    assert raw["study"]["execution"] == load_workflow_config(ROOT / "config/gpu_study.yaml")["study"]["execution"]
    # The target, an allocation at no more than 0.35 x the BF16 weight memory, lies in the space
    assert sorted(ref for ref in CANDIDATES if Candidate.from_ref(ref).cost_ratio <= 0.35) == sorted(
        f"{GROUP}/rtn-{p}-{s}" for p, s in [("W4A8", "e2e"), ("W4A4", "e2e"), ("W4", "e2e"), ("W3", "e2e"),
                                             ("W2", "e2e"), ("W3", "ve_mp_llm"), ("W2", "ve_mp_llm")])


def test_the_baseline_phase_is_the_searchs_own_baseline_on_the_whole_node():
    """config/gpu_search_baseline.yaml: the same baseline cell (its hash: how it runs is not hashed), alone, one job
    per GPU; the confirmation's two cells share the GPU two at a time."""
    (key, _), = by_ref(study_cells(SEARCH, BASE_PHASE)).values()
    assert key == by_ref(study_cells(SEARCH))[BASELINE][0]
    execution = StudyConfig.from_dict(merged(SEARCH, BASE_PHASE)["study"]).execution
    assert (execution.jobs_per_gpu, execution.num_envs) == (1, 16)  # 15 simulator workers on the 16 cores
    assert StudyConfig.from_dict(merged(SEARCH, CONFIRM)["study"]).execution.jobs_per_gpu == 2


def test_the_confirmation_runs_the_chosen_allocation_by_name_on_run_seed_1_in_full(tmp_path):
    """With the search's tables/search_chosen.yaml (here naming RTN W4 on the language model), the confirmation's
    seed1-alloc-gpu_search is the cell seed1-rtn-W4-llm: the same hash, on run seed 1, in full, beside full
    precision on run seed 1."""
    chosen = tmp_path / "search_chosen.yaml"
    chosen.write_text(yaml.safe_dump({"study": {"allocations": {"gpu_search": "rtn-W4-llm"}}}))
    cells = by_ref(study_cells(SEARCH, str(chosen), CONFIRM))
    assert sorted(cells) == [f"{GROUP}/seed1-alloc-gpu_search", f"{GROUP}/seed1-rtn-BASELINE-e2e"]
    raw = load_workflow_config(ROOT / SEARCH)
    study = StudyConfig.from_dict({**raw["study"], "sequential": None})
    spelled = cell_config(f"{GROUP}/seed1-rtn-W4-llm", study)
    assert cells[f"{GROUP}/seed1-alloc-gpu_search"][0] == config_hash(spelled)
    for _, cfg in cells.values():
        assert cfg["seed"] == 1 and "sequential" not in cfg and cfg["episodes_per_task"] == 50
    assert load_table(ROOT / "config/gpu_search/tables/gpu_search_confirm.yaml").refs() == sorted(cells)


def test_a_dry_run_plans_the_candidates_to_start_cheapest_first(tmp_path):
    """`snakemake -n` on this CPU machine (the NO_GPU refusal stated, the jobs planned all the same): the baseline
    and the 30 candidates, no calibration, each candidate after the baseline's records, and rule rollout's
    priorities in the search's order: the baseline highest, then cheapest weight memory first."""
    output = dry_run(tmp_path, SEARCH)
    assert job_count(output, "rollout") == 31 and not re.search(r"^calibrate\s", output, re.MULTILINE)
    refs = {key: cfg["ref"] for key, cfg in study_cells(SEARCH).items()}
    blocks = re.findall(r"rule rollout:\n((?:    .*\n)+)", output)
    priority = {}
    for block in blocks:
        key = re.search(r"wildcards: cell=(\w+)", block)[1]
        priority[refs[key]] = int(re.search(r"priority: (\d+)", block)[1])
    order = [c.ref for c in search_order(Candidate.from_ref(ref) for ref in CANDIDATES)]
    assert [ref for ref, _ in sorted(priority.items(), key=lambda item: -item[1])] == [BASELINE, *order]
    assert order[:5] == [f"{GROUP}/rtn-{p}-e2e" for p in ("W2", "W3", "W4", "W4A8", "W4A4")]
    baseline = next(key for key, ref in refs.items() if ref == BASELINE)
    for job in planned(output, "rollout"):  # a candidate reads the baseline's records: it waits for them
        key = re.search(r"results/cells/(\w+)/", job["output"])[1]
        assert (f"results/cells/{baseline}/episodes.parquet" in job["input"]) == (key != baseline)


def test_the_rule_decides_an_equal_candidate_within_5_points_only_where_its_episodes_rarely_disagree():
    """What a run should expect. The stopping rule reads paired differences (the same task, variation and seed in
    both cells), so its power depends on how often a candidate's episode ends otherwise than full precision's. The
    GPU study's committed cells measure it: 8-bit cells (W8A8 e2e) disagree on 4% of episodes, MXFP4 e2e, a 4-bit
    format as good on average (-1 pp), on 15%. Simulated candidates exactly as good as full precision (per-task
    success as the baseline's 200 episodes, 45-100%; outcomes flipped so as to keep each task's rate) at alpha
    0.05 / 30: at 4% disagreement 5 pp is decided `not_worse` in most runs at the 50-round cap and rarely within 20
    rounds; at 15% it is rarely decided even at the cap, while 10 pp is, in most runs. So at 5 pp the search can
    choose an 8-bit allocation (about half the weight memory), rarely a 4-bit one."""
    baseline = pd.read_parquet(GPU_BASELINE / "episodes.parquet")
    success = baseline.groupby("task_id")["success"].mean().sort_index().to_numpy()
    assert len(success) == 10 and baseline["success"].mean() == pytest.approx(0.825)

    def disagreement(cell):
        paired = pd.read_parquet(GPU_BASELINE.parent / cell / "episodes.parquet").merge(
            baseline, on=["task_id", "episode", "seed"], suffixes=("", "_fp"))
        assert len(paired) == 200
        return (paired["success"] != paired["success_fp"]).mean()

    rng = np.random.default_rng(0)

    def not_worse(margin, rounds, rate, runs=60):
        design = SearchDesign(0.05, margin).per_candidate(30)
        # Flip success to failure with d / 2p and failure to success with d / 2(1 - p): d disagree, the rate stays.
        to_fail = np.where(success > 0, rate / (2 * np.maximum(success, 1e-9)), 0).clip(max=1)
        to_success = np.where(success < 1, rate / (2 * np.maximum(1 - success, 1e-9)), 0).clip(max=1)
        decided = 0
        for _ in range(runs):
            full = (rng.random((rounds, 10)) < success).astype(int)
            flip = rng.random((rounds, 10)) < np.where(full == 1, to_fail, to_success)
            decided += stopping_rule(np.where(flip, 1 - full, full) - full, design).decision == "not_worse"
        return decided / runs

    eight_bit, four_bit = disagreement("rtn-W8A8-e2e"), disagreement("rtn-MXFP4-e2e")
    assert (eight_bit, four_bit) == (pytest.approx(0.04), pytest.approx(0.15))
    assert not_worse(5, 50, eight_bit) >= 0.6 and not_worse(5, 20, eight_bit) <= 0.15
    assert not_worse(5, 50, four_bit) <= 0.2 and not_worse(10, 50, four_bit) >= 0.5


def script(checkout: Path, *args: str, **env) -> subprocess.CompletedProcess:
    return subprocess.run(["bash", str(SCRIPT), *args], cwd=checkout, capture_output=True, text=True, timeout=300,
                          env={**os.environ, "PYTHON": sys.executable, **env})


def progress_rows(rows: dict[str, tuple[int, int, str]]) -> str:
    """The carried progress (results/gpu_search_progress.tsv) of finished search cells: ref -> (episodes,
    finished, decision), by the search config's hashes."""
    keys = {cfg["ref"]: key for key, cfg in study_cells(SEARCH).items()}
    lines = ["hash\tref\tpreset\tsequential\tepisodes\tfinished\tdecision"]
    for name, (episodes, finished, decision) in rows.items():
        ref = f"{GROUP}/{name}"
        lines.append(f"{keys[ref]}\t{ref}\t{name.split('-')[1]}\t{int(name != 'rtn-BASELINE-e2e')}\t{episodes}\t"
                     f"{finished}\t{decision}")
    return "\n".join(lines) + "\n"


def test_the_device_call_knows_when_the_search_is_determined_and_what_the_confirmation_runs(tmp_path):
    """`search-state` decides the search from the finished candidates' live decisions (the carried progress):
    determined once the cheaper candidates are decided (or at their cap) and a not_worse ends it, its choice
    written to tables/search_chosen.yaml, which the confirmation phase (skipped before) then runs on run seed 1;
    not determined while a cheaper candidate is unfinished, naming it."""
    checkout = tmp_path / "checkout"
    checkout.mkdir()
    for item in ("Snakefile", "rules", "workflow", "config", "src", "checkpoints", "benchmarks"):
        (checkout / item).symlink_to(ROOT / item)
    (checkout / "results").mkdir()
    progress = checkout / "results" / "gpu_search_progress.tsv"
    finished = {"rtn-BASELINE-e2e": (500, 1, ""), "rtn-W2-e2e": (40, 1, "worse"),
                "rtn-W4-e2e": (500, 1, "undecided"), "rtn-W4A8-e2e": (330, 1, "not_worse"),
                "rtn-W3-e2e": (120, 0, "")}  # W3 e2e part-way: a journal carried
    progress.write_text(progress_rows(finished))
    plan = script(checkout, "plan")  # each phase as the next call sees it
    assert plan.returncode == 0, plan.stderr
    assert "search: not determined yet: the search is not determined by the recorded candidates: it reaches " \
           f"{GROUP}/rtn-W3-e2e (#2 of 30 in search order), which has no finished records (decided before it: " \
           "rtn-W2-e2e worse); the 27 candidate(s) without records it may still read: rtn-W3-e2e, rtn-W4A4-e2e, " in plan.stdout
    assert "skipped: tables/search_chosen.yaml does not exist" in plan.stdout

    progress.write_text(progress_rows({**finished, "rtn-W3-e2e": (150, 1, "worse")}))
    state = script(checkout, "search-state", SEARCH)
    assert state.returncode == 0, state.stdout + state.stderr
    assert f"search: determined: chosen: {GROUP}/rtn-W4A8-e2e; episodes: 1020 read by the search" in state.stdout
    chosen = checkout / "tables" / "search_chosen.yaml"
    assert yaml.safe_load(chosen.read_text()) == {"study": {"allocations": {"gpu_search": "rtn-W4A8-e2e"}}}
    plan = script(checkout, "plan")
    assert plan.returncode == 0, plan.stderr
    confirm = plan.stdout.split(f"config/gpu_search.yaml tables/search_chosen.yaml {CONFIRM}:\n", 1)[1].splitlines()
    expected = by_ref(study_cells(SEARCH, str(chosen), CONFIRM))
    assert sorted(confirm) == sorted(f"{key} {ref} 0" for ref, (key, _) in expected.items())


def test_the_device_call_the_script_documents_fits_the_device_tool():
    """Its header's `run(...)`: a command of at most 2,000 characters, at most 8 carried paths, both git-ignored."""
    header = SCRIPT.read_text().split("\nexport ", 1)[0]
    call = re.search(r"run\((.*?)\)\n", header.replace("\n#       ", " "), re.DOTALL)[1]
    command = re.search(r'command="([^"]*)"', call)[1]
    carry = re.findall(r'"([^"]+)"', re.search(r"carry=\[([^\]]*)\]", call)[1])
    assert len(command) <= 2000 and carry == [".gpuwork/study-stack", ".carry/gpu_search"]
    ignored = subprocess.run(["git", "check-ignore", *carry], cwd=ROOT, capture_output=True, text=True).stdout.split()
    assert ignored == carry
    assert subprocess.run(["bash", "-n", str(SCRIPT)]).returncode == 0
