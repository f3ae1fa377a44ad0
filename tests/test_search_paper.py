"""The precision search on LIBERO with the released pi0.5 checkpoint (issue 52, `config/search_paper.yaml`), one
config away: its space is components x {W8A8, W4A8, W4A4, W4, W3, W2} under the search's own live rule, and a dry
run on this CPU machine plans exactly those cells (their config hashes), the checkpoint's download and the search;
its confirmation (`config/search_paper_confirm.yaml`) runs the chosen allocation by name on run seed 1."""

import re
import subprocess
import sys

import numpy as np
import pytest
import yaml
from test_dag_trained_checkpoint import workflow_with_tables

from vlaquantbench.cells import cell_config, config_hash
from vlaquantbench.config import load_workflow_config
from vlaquantbench.config.study import StudyConfig
from vlaquantbench.search import Candidate, SearchDesign, check_live_design
from vlaquantbench.sequential import stopping_rule
from vlaquantbench.tables import load_table
from vlaquantbench.workflow import WorkflowConfig
from paths import ROOT

GROUP = "libero/libero_spatial/pi05"
BASELINE = f"{GROUP}/rtn-BASELINE-e2e"
SCOPES = ("ve", "llm", "ah", "ve_mp_llm", "e2e")
FORMATS = ("W8A8", "W4A8", "W4A4", "W4", "W3", "W2")
CANDIDATES = [f"{GROUP}/rtn-{preset}-{scope}" for scope in SCOPES for preset in FORMATS]


def test_the_space_is_components_by_formats_under_the_searchs_own_live_rule():
    raw = load_workflow_config(ROOT / "config/search_paper.yaml")
    paper = load_workflow_config(ROOT / "config/paper.yaml")
    study = StudyConfig.from_dict(raw["study"])
    assert study.models["pi05"] == StudyConfig.from_dict(paper["study"]).models["pi05"]  # the released checkpoint
    assert (study.runner.device, study.runner.dtype, study.task_ids, study.episodes_per_task) == ("cuda", "bfloat16",
                                                                                                list(range(10)), 50)
    workflow = WorkflowConfig.from_snakemake(raw, ROOT)
    refs = list(dict.fromkeys(workflow.table(raw["search"]["table"]).refs()))
    assert sorted(refs) == sorted([BASELINE, *CANDIDATES])
    design = SearchDesign(raw["search"]["alpha"], raw["search"]["margin_pp"])
    live = study.sequential
    check_live_design(design, len(CANDIDATES), BASELINE, live.alpha, live.margin_pp, live.against)  # no refusal
    assert (design.alpha, design.margin_pp, live.alpha) == (0.05, 5, pytest.approx(0.05 / 30, rel=1e-15))
    # The target, an allocation at no more than 0.35 x the BF16 weight memory, lies in the space
    costs = {ref: Candidate.from_ref(ref).cost_ratio for ref in CANDIDATES}
    assert sorted(ref for ref, cost in costs.items() if cost <= 0.35) == sorted(
        f"{GROUP}/rtn-{p}-{s}" for p, s in [("W4A8", "e2e"), ("W4A4", "e2e"), ("W4", "e2e"), ("W3", "e2e"),
                                             ("W2", "e2e"), ("W3", "ve_mp_llm"), ("W2", "ve_mp_llm")])
    for ref in CANDIDATES:  # each candidate stops against full precision at the per-candidate level
        cfg = cell_config(ref, study)
        assert cfg["sequential"]["alpha"] == live.alpha and cfg["sequential"]["against"]["ref"] == BASELINE
    assert load_table(ROOT / "config/search_paper/tables/search_paper_confirm.yaml").refs() == [
        f"{GROUP}/seed1-alloc-search_paper", f"{GROUP}/seed1-rtn-BASELINE-e2e"]


def _dry_run(checkout, target, *configs):
    result = subprocess.run([sys.executable, "-m", "snakemake", "-n", "--cores", "8", target, "--configfile", *configs],
                            cwd=checkout, capture_output=True, text=True, timeout=600)
    planned = re.findall(r"rule rollout:\n(?:    .*\n)*?    wildcards: cell=([0-9a-f]{12})", result.stdout)
    return result, planned


def test_a_dry_run_plans_the_candidates_the_download_and_the_search(tmp_path):
    """On a machine without a GPU or the hub: every cell of the space once (the hashes the study gives them, each
    candidate under its live rule), the checkpoint's download at its revision, then the search; a live rule at
    another level is refused naming the level to set."""
    checkout, _ = workflow_with_tables(tmp_path)
    result, planned = _dry_run(checkout, "tables/search.csv", "config/search_paper.yaml")
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    study = StudyConfig.from_dict(load_workflow_config(ROOT / "config/search_paper.yaml")["study"])
    assert sorted(planned) == sorted(config_hash(cell_config(ref, study)) for ref in [BASELINE, *CANDIDATES])
    assert "checkpoint=pi05-full-8e174154ef5f" in result.stdout
    assert result.stdout.count("rule search_table:") == 1 and "tables/search_chosen.yaml" in result.stdout

    level = tmp_path / "level.yaml"
    level.write_text("study: {sequential: {alpha: 0.05, margin_pp: 5, against: rtn-BASELINE-e2e}}\n")
    refused, _ = _dry_run(checkout, "tables/search.csv", "config/search_paper.yaml", str(level))
    assert refused.returncode != 0
    assert "set alpha 0.00166667 (search.alpha 0.05 / 30 candidates) and margin_pp 5" in refused.stdout + refused.stderr


def test_the_confirmation_runs_the_chosen_allocation_by_name_on_run_seed_1(tmp_path):
    """With the search's tables/search_chosen.yaml (here naming RTN W4 end to end), seed1-alloc-search_paper is
    the cell seed1-rtn-W4-e2e: the dry run plans it and the baseline on run seed 1, in full; without that file the
    DAG is refused, naming the allocation and where allocations are defined."""
    checkout, _ = workflow_with_tables(tmp_path)
    chosen = tmp_path / "search_chosen.yaml"
    chosen.write_text(yaml.safe_dump({"study": {"allocations": {"search_paper": "rtn-W4-e2e"}}}))
    configs = ("config/search_paper.yaml", str(chosen), "config/search_paper_confirm.yaml")
    result, planned = _dry_run(checkout, "tables/search_paper_confirm.tex", *configs)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    raw = load_workflow_config(ROOT / "config/search_paper.yaml")
    study = StudyConfig.from_dict({**raw["study"], "sequential": None, "allocations": {"search_paper": "rtn-W4-e2e"}})
    spelled = [cell_config(f"{GROUP}/seed1-{name}", study) for name in ("rtn-W4-e2e", "rtn-BASELINE-e2e")]
    assert sorted(planned) == sorted(config_hash(cfg) for cfg in spelled)
    assert all(cfg["seed"] == 1 and "sequential" not in cfg for cfg in spelled)

    refused, _ = _dry_run(checkout, "tables/search_paper_confirm.tex", configs[0], configs[2])
    assert refused.returncode != 0
    assert ("cell 'libero/libero_spatial/pi05/seed1-alloc-search_paper': unknown allocation 'search_paper': "
            "study.allocations defines none") in refused.stdout + refused.stderr


def test_the_cap_gives_the_rule_the_power_to_decide_not_worse():
    """A candidate as good as full precision (both 99% on every task) is decided `not_worse` at the config's level
    and margin in most simulated runs within its 50 rounds, but rarely within the paper's 20: why the config runs
    every init state of the suite."""
    raw = load_workflow_config(ROOT / "config/search_paper.yaml")
    design = SearchDesign(raw["search"]["alpha"], raw["search"]["margin_pp"]).per_candidate(len(CANDIDATES))
    rounds = raw["study"]["episodes_per_task"]
    rng = np.random.default_rng(0)

    def decided(cap):
        outcomes = (rng.random((100, 2, cap, 10)) < 0.99).astype(int)
        return [stopping_rule(a - b, design) for a, b in outcomes]

    capped, paper = decided(rounds), decided(20)
    assert sum(r.decision == "not_worse" for r in capped) >= 90
    assert sum(r.decision == "not_worse" for r in paper) <= 15
    assert np.mean([r.rounds_used for r in capped]) < 0.7 * rounds  # the rule stops early where it decides
