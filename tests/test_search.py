"""Closed-loop precision search (issue 52): costs from the committed layer index, the dominance that prunes, the
search over recorded cells (the authors' LIBERO lattice, the pi0.5 trained here) against deciding every candidate,
`vqb search`'s refusals, the episodes it reports, and the chosen allocation by name (`alloc-<name>` cells)."""

import csv
import re
import subprocess
import sys

import pandas as pd
import pytest
import yaml
from file_audit import audited_env, job_audits, undeclared
from test_dag_trained_checkpoint import workflow_with_tables

from vlaquantbench.cells import cell_config, config_hash
from vlaquantbench.cli import main
from vlaquantbench.config.study import StudyConfig
from vlaquantbench.errors import UserError
from vlaquantbench.models.layer_index import selected_counts
from vlaquantbench.records import find_cells, read_cell
from vlaquantbench.search import (Candidate, SearchDesign, Verdict, at_least_as_aggressive, exhaustive,
                                  precision_search, records_decider, weight_bits)
from vlaquantbench.sequential import retrospective
from vlaquantbench.tables.search import CHOSEN_FILE
from paths import RECORDS, ROOT

SPATIAL = "libero/libero_spatial/pi05"
TRAINED = "metaworld/metaworld_mt50/pi05"
TRAINED_FIXED = ROOT / "results" / "trained_sequential" / "fixed"
TRAINED_LIVE = ROOT / "results" / "trained_sequential" / "live"
CONFIRM = ROOT / "results" / "trained_search" / "confirm"


def _space(records_dir, group):
    """The candidates of `group`'s cells in `records_dir` (all but its BASELINE cell) and every cell's records."""
    cells = {ref: read_cell(path) for ref, path in find_cells(records_dir).items() if ref.startswith(group + "/")}
    baseline = f"{group}/rtn-BASELINE-e2e"
    candidates = [Candidate.from_ref(ref) for ref in cells if ref != baseline]
    decide = records_decider({r: c.episodes for r, c in cells.items()}, {r: c.header for r, c in cells.items()}, baseline)
    return candidates, decide, cells, baseline


def test_cost_is_weight_memory_on_the_layer_index():
    counts = selected_counts("pi05", "e2e")
    total = sum(c["params"] for c in counts.values())
    assert Candidate.from_ref(f"{SPATIAL}/rtn-BASELINE-e2e").cost_ratio == 1.0
    # 4-bit asymmetric groups of 128: 4 bits + a 16-bit scale and a 16-bit zero point per 128 weights
    assert Candidate.from_ref(f"{SPATIAL}/rtn-W4A4-e2e").cost_ratio == pytest.approx((4 + 32 / 128) / 16)
    assert Candidate.from_ref(f"{SPATIAL}/rtn-W8A8-e2e").cost_ratio == pytest.approx(8 / 16)  # per channel
    ah = counts["ah"]["params"]
    assert Candidate.from_ref(f"{SPATIAL}/rtn-W4A8-ah").cost_ratio == pytest.approx(
        (ah * 4.25 + (total - ah) * 16) / (total * 16))
    subset = Candidate.from_ref(f"{SPATIAL}/ablate-W4A4-ah-onlyself_attn")
    assert len(subset.layers) == 72 and sum(subset.layers.values()) == 84934656  # config/scopes.yaml's counts
    assert weight_bits(subset.preset) == 4.25
    assert [weight_bits(Candidate.from_ref(f"{SPATIAL}/fp8-{p}-ah").preset) for p in ("FP8E4M3", "MXFP4", "NVFP4")] \
        == [8, 4 + 8 / 32, 4 + 8 / 16]


def test_dominance_needs_same_method_more_layers_and_fewer_bits():
    def cand(name):
        return Candidate.from_ref(f"{SPATIAL}/{name}")

    assert at_least_as_aggressive(cand("rtn-W4A4-e2e"), cand("rtn-W4A8-ah"))
    assert not at_least_as_aggressive(cand("rtn-W4A8-ah"), cand("rtn-W4A4-e2e"))
    assert at_least_as_aggressive(cand("rtn-W4A4-ah"), cand("ablate-W4A4-ah-onlyself_attn"))  # ablate is RTN
    assert not at_least_as_aggressive(cand("calib_ah-W4A4-ah"), cand("ablate-W4A4-ah-onlyself_attn"))
    assert not at_least_as_aggressive(cand("gptq-W4A4-e2e"), cand("rtn-W4A8-e2e"))
    assert not at_least_as_aggressive(cand("rtn-W2-e2e"), cand("rtn-W4A8-e2e"))  # fewer weight bits, more act bits


def test_search_on_the_authors_lattice_chooses_what_deciding_every_candidate_chooses():
    """pi0.5 on LIBERO-Spatial, the authors' 22 quantized cells (200 episodes each), margin 10 pp: the search
    stops at the cheapest `not_worse`, reads fewer episodes than the 22 cells in full, and each decision it made
    is the one `vlaquantbench.sequential.retrospective` gives that contrast at alpha / 22."""
    candidates, decide, cells, baseline = _space(RECORDS, SPATIAL)
    design = SearchDesign(alpha=0.05, margin_pp=10.0)
    result = precision_search(candidates, decide, design)
    chosen, verdicts = exhaustive(candidates, decide, design)
    assert len(candidates) == 22 and result.chosen is not None and result.chosen.ref == chosen.ref
    assert result.chosen.cost_ratio == min(c.cost_ratio for c in candidates if verdicts[c.ref].decision == "not_worse")
    assert result.episodes_spent < result.episodes_exhaustive == 22 * 200
    replay = retrospective([(ref, baseline) for ref in result.verdicts], {r: c.episodes for r, c in cells.items()},
                           design.per_candidate(22), family="none")
    assert dict(zip(replay["cell"], replay["decision"])) == {r: v.decision for r, v in result.verdicts.items()}
    assert dict(zip(replay["cell"], replay["episodes_used"])) == {r: v.episodes_used for r, v in result.verdicts.items()}


def test_search_on_the_trained_policy_records():
    """The pi0.5 trained here, its full-precision, RTN W4A8 and W2A2 cells run in full (60 episodes): at alpha
    0.05 over 2 candidates W2A2 is `worse` after 12 rounds, as the live rule at 0.05 decided, and W4A8 is decided
    `not_worse` within 20 pp; within 5 pp nothing is chosen."""
    candidates, decide, _, _ = _space(TRAINED_FIXED, TRAINED)
    result = precision_search(candidates, decide, SearchDesign(0.05, 20.0))
    assert result.chosen.ref == f"{TRAINED}/rtn-W4A8-e2e"
    assert result.verdicts[f"{TRAINED}/rtn-W2A2-e2e"].decision == "worse"
    assert result.verdicts[f"{TRAINED}/rtn-W2A2-e2e"].episodes_used == 36
    assert precision_search(candidates, decide, SearchDesign(0.05, 5.0)).chosen is None


def test_worse_prunes_the_more_aggressive_and_not_worse_ends_the_search():
    """The search's own logic, given verdicts (the stopping rule is the test above's): at equal cost W4A8 comes
    before W4A4, a `worse` W4A8 prunes W4A4 on the same layers, and the first `not_worse` ends the search."""
    names = ["rtn-W4A4-e2e", "rtn-W4A8-e2e", "gptq-W4A8-e2e", "rtn-W4A8-ah", "rtn-W8A8-ah"]
    candidates = [Candidate.from_ref(f"{SPATIAL}/{name}") for name in names]
    verdicts = {"rtn-W4A8-e2e": "worse", "gptq-W4A8-e2e": "undecided", "rtn-W4A8-ah": "not_worse"}
    visited = []

    def decide(candidate, design):
        visited.append(candidate.ref.rsplit("/", 1)[-1])
        assert design.alpha == pytest.approx(0.01)  # alpha split over the 5 candidates
        return Verdict(verdicts[visited[-1]], 6, 10)

    result = precision_search(candidates, decide, SearchDesign(0.05, 5.0))
    assert visited == ["gptq-W4A8-e2e", "rtn-W4A8-e2e", "rtn-W4A8-ah"]  # equal costs: by name
    assert result.pruned_by == {f"{SPATIAL}/rtn-W4A4-e2e": f"{SPATIAL}/rtn-W4A8-e2e"}
    assert result.status(f"{SPATIAL}/rtn-W8A8-ah") == "not reached"
    assert result.chosen.ref == f"{SPATIAL}/rtn-W4A8-ah" and result.episodes_spent == 18
    assert result.episodes_exhaustive == 50


def test_vqb_search_writes_the_candidates_and_the_choice(tmp_path, capsys):
    out = tmp_path / "search.csv"
    assert main(["search", str(TRAINED_FIXED), "--margin", "20", "--exhaustive", "--csv", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "chosen: metaworld/metaworld_mt50/pi05/rtn-W4A8-e2e" in printed and "(the same)" in printed
    assert "alpha 0.05 split over the 2 candidates" in printed and "93 of 120" in printed
    rows = list(csv.DictReader(out.open()))
    assert [r["status"] for r in rows] == ["baseline (runs in full)", "visited", "chosen"]
    assert [r["pareto"] for r in rows] == ["True", "True", "True"]


@pytest.mark.parametrize("args, message", [
    (["--alpha", "1.5"], "alpha must lie in (0, 1)"),
    (["--baseline", "rtn-W8A8-e2e"], "0 such cells"),
    (["--cells", "awq-*"], "matches --cells awq-*"),
])
def test_vqb_search_refuses_bad_input(tmp_path, capsys, args, message):
    assert main(["search", str(TRAINED_FIXED), *args, "--csv", str(tmp_path / "s.csv")]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "s.csv").exists()


def test_live_stopped_records_are_searched_only_at_their_level(tmp_path, capsys):
    """The live W2A2 cell stopped at alpha 0.05: one candidate (alpha / 1) reads it, two (alpha / 2) refuse it."""
    out = tmp_path / "s.csv"
    assert main(["search", str(TRAINED_LIVE), "--cells", "rtn-W2A2-e2e", "--csv", str(out)]) == 0
    assert [r["decision"] for r in csv.DictReader(out.open())][1:] == ["worse"]
    assert main(["search", str(TRAINED_LIVE), "--csv", str(out)]) == 2
    assert "rtn-W2A2-e2e: its records were stopped by a live rule at alpha 0.05" in capsys.readouterr().err


@pytest.mark.slow
def test_snakemake_searches_the_trained_policy_from_its_committed_records(tmp_path):
    """tables/search.csv, figures/search_pareto.pdf and tables/search_chosen.yaml through Snakemake from the
    committed records (no episode runs): the same choice as `vqb search` on the folder and as deciding every
    candidate, named as search.allocation says; a config without a `search` section is refused naming it."""
    checkout, _ = workflow_with_tables(tmp_path)
    (checkout / "results").mkdir()
    (checkout / "results/trained_sequential").symlink_to(ROOT / "results/trained_sequential")
    (checkout / "manifests").mkdir()
    (checkout / "manifests/trained_sequential_fixed.tsv").symlink_to(ROOT / "manifests/trained_sequential_fixed.tsv")
    (checkout / "results/trained_search").symlink_to(ROOT / "results/trained_search")
    (checkout / "manifests/trained_search_confirm.tsv").symlink_to(ROOT / "manifests/trained_search_confirm.tsv")
    configs = ["config/trained_sequential.yaml", "config/trained_sequential_fixed.yaml"]

    audit = tmp_path / "audit"

    def snakemake(*configs):
        return subprocess.run([sys.executable, "-m", "snakemake", "--cores", "2", "tables/search.csv", "--configfile",
                               *configs], cwd=checkout, capture_output=True, text=True, timeout=600,
                              env=audited_env(audit))

    refused = snakemake(*configs)
    assert refused.returncode != 0 and "needs a `search` section" in refused.stderr
    result = snakemake(*configs, "config/trained_search.yaml")
    assert result.returncode == 0, result.stderr[-3000:]
    assert "rule rollout" not in result.stdout + result.stderr
    log = (checkout / "logs/tables/search.log").read_text()
    assert f"chosen: {TRAINED}/rtn-W4A8-e2e" in log and "(the same)" in log and "confirmed_not_worse" in log
    table = pd.read_csv(checkout / "tables/search.csv").set_index("cell")
    assert table.at[f"{TRAINED}/rtn-W2A2-e2e", "decision"] == "worse"
    assert table.at[f"{TRAINED}/rtn-W4A8-e2e", "status"] == "chosen"
    assert (checkout / "figures/search_pareto.pdf").read_bytes().startswith(b"%PDF")
    chosen = yaml.safe_load((checkout / CHOSEN_FILE).read_text())
    assert chosen == {"study": {"allocations": {"trained_search": "rtn-W4A8-e2e"}}}
    assert [job["rule"] for job in job_audits(audit)] == ["search_table"]
    assert undeclared(audit, checkout) == {}  # the job touched only the files its rule declares


def test_the_chosen_cell_is_confirmed_on_held_out_episodes(tmp_path, capsys):
    """RTN W4A8 e2e, chosen within 20 pp, against full precision on run seed 1 (60 episodes each, never read by the
    search): -5.0 pp, bootstrap [-15.0, +3.3], above -20: confirmed."""
    out = tmp_path / "s.csv"
    assert main(["search", str(TRAINED_FIXED), "--margin", "20", "--confirm-seed", "1", "--confirm-dir", str(CONFIRM),
                 "--csv", str(out)]) == 0
    assert "-5.0 pp [-15.0, +3.3] (task-clustered bootstrap 95%): confirmed_not_worse" in capsys.readouterr().out
    chosen = next(r for r in csv.DictReader(out.open()) if r["status"] == "chosen")
    assert chosen["confirm_cell"] == f"{TRAINED}/seed1-rtn-W4A8-e2e" and float(chosen["confirm_episodes"]) == 60
    held = {ref: read_cell(path) for ref, path in find_cells(CONFIRM).items()}
    search = {ref: read_cell(path) for ref, path in find_cells(TRAINED_FIXED).items()}
    for ref, cell in held.items():  # other episodes: the same tasks and variations, other seeds
        same = search[ref.replace("seed1-", "")].episodes
        assert list(cell.episodes["task_id"]) == list(same["task_id"]) and not set(cell.episodes["seed"]) & set(same["seed"])


def test_confirmation_needs_the_held_out_records_and_a_new_seed(tmp_path, capsys):
    out = tmp_path / "s.csv"
    assert main(["search", str(TRAINED_FIXED), "--margin", "20", "--confirm-seed", "1", "--csv", str(out)]) == 2
    assert (f"the confirmation needs the records of {TRAINED}/seed1-rtn-W4A8-e2e, {TRAINED}/seed1-rtn-BASELINE-e2e"
            in capsys.readouterr().err)
    assert main(["search", str(TRAINED_FIXED), "--confirm-seed", "0", "--csv", str(out)]) == 2
    assert "the confirmation's run seed must be 1 or more" in capsys.readouterr().err


def _dry_run(checkout, *configs):
    return subprocess.run([sys.executable, "-m", "snakemake", "-n", "--cores", "2", "tables/search.csv", "--configfile",
                           "config/trained_sequential.yaml", "config/trained_search.yaml", *map(str, configs),
                           "--config", "records_dir=", "manifest="],
                          cwd=checkout, capture_output=True, text=True, timeout=600)


def test_a_dag_that_runs_the_candidates_live_must_run_the_searchs_rule(tmp_path):
    """Without records the DAG runs the space's cells under study.sequential: at alpha 0.05 for 2 candidates it is
    refused while the DAG is built, naming the level to set; at 0.025 it plans the baseline and both candidates
    once the confirmation's records folder exists (refused naming it before)."""
    checkout, _ = workflow_with_tables(tmp_path)
    refused = _dry_run(checkout)
    assert refused.returncode != 0
    assert "set alpha 0.025 (search.alpha 0.05 / 2 candidates) and margin_pp 20" in refused.stdout + refused.stderr
    level = tmp_path / "level.yaml"
    level.write_text("study: {sequential: {alpha: 0.025, margin_pp: 20, against: rtn-BASELINE-e2e}}\n")
    refused = _dry_run(checkout, level)
    assert refused.returncode != 0
    assert "search.confirm.records_dir results/trained_search/confirm is not a folder" in refused.stdout + refused.stderr
    (checkout / "results").mkdir()
    (checkout / "results/trained_search").symlink_to(ROOT / "results/trained_search")
    (checkout / "manifests").symlink_to(ROOT / "manifests")
    planned = _dry_run(checkout, level)
    assert planned.returncode == 0, planned.stdout[-3000:]
    assert planned.stdout.count("rule rollout:") == 3 and "rule search_table:" in planned.stdout


def _merged(*paths):
    """The config `snakemake --configfile PATHS...` runs with: each file merged over the last (Snakemake's own merge)."""
    from snakemake.utils import update_config

    config = {}
    for path in (ROOT / "config/config.yaml", *paths):
        update_config(config, yaml.safe_load(path.read_text()))
    return config


def test_the_chosen_allocation_is_a_named_cell_that_runs_as_the_chosen_one(tmp_path, capsys):
    """`--chosen` writes study.allocations.<name> = the chosen cell's name; added after the study's config, the
    cell `alloc-<name>` (and its held-out `seed1-alloc-<name>`) hashes as the chosen cell, so it is that cell's
    folder and records. Every episode is counted: read by the search, recorded, and every candidate in full."""
    out, chosen = tmp_path / "s.csv", tmp_path / "chosen.yaml"
    assert main(["search", str(TRAINED_FIXED), "--margin", "20", "--csv", str(out), "--chosen", str(chosen),
                 "--allocation", "trained"]) == 0
    assert "recorded: 120 episodes in the 2 candidates' records (100% of every candidate in full)" in capsys.readouterr().out
    assert yaml.safe_load(chosen.read_text()) == {"study": {"allocations": {"trained": "rtn-W4A8-e2e"}}}
    assert "# episodes: 93 of 120 that every candidate run in full would need" in chosen.read_text()
    rows = pd.read_csv(out)
    assert rows["episodes_used"].iloc[1:].sum() == 93 and list(rows["episodes_full"]) == [60, 60, 60]
    assert list(rows["episodes_recorded"]) == [60, 60, 60]

    configs = [ROOT / "config/trained_sequential.yaml", ROOT / "config/trained_sequential_fixed.yaml"]
    study = StudyConfig.from_dict(_merged(*configs, chosen)["study"])
    for prefix in ("", "seed1-"):
        named = cell_config(f"{TRAINED}/{prefix}alloc-trained", study)
        assert config_hash(named) == config_hash(cell_config(f"{TRAINED}/{prefix}rtn-W4A8-e2e", study))
        assert named["preset"] == "W4A8" and named["scope"] == "e2e"
    without = StudyConfig.from_dict(_merged(*configs)["study"])
    with pytest.raises(UserError, match="unknown allocation 'trained': study.allocations defines none"):
        cell_config(f"{TRAINED}/alloc-trained", without)

    # Nothing decided not_worse (5 pp): no allocation is named, so the name is refused
    assert main(["search", str(TRAINED_FIXED), "--csv", str(out), "--chosen", str(chosen), "--allocation", "trained"]) == 0
    assert yaml.safe_load(chosen.read_text()) == {"study": {"allocations": {}}}
    with pytest.raises(UserError, match="unknown allocation 'trained'"):
        cell_config(f"{TRAINED}/alloc-trained", StudyConfig.from_dict(_merged(*configs, chosen)["study"]))


def test_a_bad_allocation_name_is_refused_before_anything_is_written(tmp_path, capsys):
    out, chosen = tmp_path / "s.csv", tmp_path / "chosen.yaml"
    assert main(["search", str(TRAINED_FIXED), "--margin", "20", "--csv", str(out), "--chosen", str(chosen),
                 "--allocation", "W4-best"]) == 2
    assert "allocation 'W4-best': study.allocations: 'W4-best' does not match '^[a-z0-9_]+$'" in capsys.readouterr().err
    assert not out.exists() and not chosen.exists()


def test_a_named_allocation_reads_the_chosen_cells_records_from_a_records_folder(tmp_path):
    """From a records folder a cell is read by its reference: `alloc-<name>` reads the records of the cell it
    stands for (not recorded under its own name), checked by the manifest as that cell; unknown is refused."""
    from vlaquantbench.workflow import WorkflowConfig

    chosen = tmp_path / "chosen.yaml"
    chosen.write_text(yaml.safe_dump({"study": {"allocations": {"trained_search": "rtn-W4A8-e2e"}}}))
    raw = _merged(ROOT / "config/trained_sequential.yaml", ROOT / "config/trained_sequential_fixed.yaml", chosen)
    workflow = WorkflowConfig.from_snakemake(raw, ROOT)
    named, spelled = f"{TRAINED}/alloc-trained_search", f"{TRAINED}/rtn-W4A8-e2e"
    assert workflow.record_refs([named], "t") == [named] and workflow.checked_refs([named], "t") == [named]
    assert workflow.cell_input(named) == workflow.cell_input(spelled)
    assert workflow.cell_header(named).endswith("rtn-W4A8-e2e/header.json")
    unknown = WorkflowConfig.from_snakemake({**raw, "study": {**raw["study"], "allocations": {}}}, ROOT)
    with pytest.raises(UserError, match="unknown allocation 'trained_search': study.allocations defines none"):
        unknown.record_refs([named], "t")


@pytest.mark.slow
def test_snakemake_renders_a_table_row_of_the_named_allocation_as_the_chosen_cell(tmp_path):
    """The search's own tables/search_chosen.yaml, added after the study's configs: a table whose rows are the
    chosen cell and its name renders them alike, from the committed records (no episode runs)."""
    checkout, tables = workflow_with_tables(tmp_path)
    (checkout / "results").mkdir()
    (checkout / "results/trained_sequential").symlink_to(ROOT / "results/trained_sequential")
    (checkout / "manifests").mkdir()
    (checkout / "manifests/trained_sequential_fixed.tsv").symlink_to(ROOT / "manifests/trained_sequential_fixed.tsv")
    assert main(["search", str(TRAINED_FIXED), "--margin", "20", "--csv", str(tmp_path / "s.csv"),
                 "--chosen", str(checkout / "chosen.yaml"), "--allocation", "trained_search"]) == 0
    (tables / "named.yaml").write_text(yaml.safe_dump({
        "caption": "c", "align": "lrrrr", "header": [["Cell", "Episodes", "Success", "Layers", "Params"]],
        "values": [{"stat": "episodes", "cell": "cell"}, {"stat": "rate", "cell": "cell"},
                   {"stat": "layers", "cell": "cell"}, {"stat": "params", "cell": "cell", "digits": 2}],
        "rows": [{"label": "spelled", "cell": f"{TRAINED}/rtn-W4A8-e2e"},
                 {"label": "named", "cell": f"{TRAINED}/alloc-trained_search"}]}))
    result = subprocess.run([sys.executable, "-m", "snakemake", "--cores", "1", "tables/named.tex", "--configfile",
                             "config/trained_sequential.yaml", "config/trained_sequential_fixed.yaml", "chosen.yaml",
                             "--config", f"tables_dir={tables}"],
                            cwd=checkout, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "rule rollout" not in result.stdout + result.stderr
    body = (checkout / "tables/named.tex").read_text()
    spelled, named = (re.search(rf"^{label} & (.*)\\\\", body, re.MULTILINE)[1] for label in ("spelled", "named"))
    assert spelled == named and named.startswith("60 & ")
    assert len(named.split("&")) == 4 and named.split("&")[2].strip() != "--"  # the chosen cell's quantized layers


# --- a space recorded in part: a run cut short, its candidates started cheapest first -------------------------------
def _space_table(path, refs):
    """A table definition whose cells are `refs`: what `vqb search --space` and the target read as the whole space."""
    path.write_text(yaml.safe_dump({"caption": "space", "align": "lr", "header": [["Cell", "Episodes"]],
                                    "values": [{"stat": "episodes", "cell": "cell"}],
                                    "rows": [{"label": str(i), "cell": ref} for i, ref in enumerate(refs)]}))
    return path


def _prefix(folder, records, refs):
    """A records folder holding only `refs` of `records` (links to their files, in the folder's layout)."""
    found = find_cells(records)
    for ref in refs:
        target = folder / found[ref].relative_to(records)
        target.parent.mkdir(parents=True, exist_ok=True)
        target.symlink_to(found[ref])
    return folder


def test_a_recorded_prefix_that_determines_the_search_gives_its_answer(tmp_path, capsys):
    """The authors' pi0.5 LIBERO-Spatial lattice at 10 pp, as if the run had stopped once the search was determined:
    only the baseline and the two cheapest candidates recorded (the first undecided at its cap, the second
    `not_worse`). Searched over the whole space of 22 (alpha / 22 each), it chooses what the search over every
    record chooses, with the same decisions and episodes; the 20 unrecorded candidates are `not reached`."""
    baseline = f"{SPATIAL}/rtn-BASELINE-e2e"
    space = sorted(ref for ref in find_cells(RECORDS) if ref.startswith(SPATIAL + "/"))
    table = _space_table(tmp_path / "space.yaml", space)
    full, part = tmp_path / "full.csv", tmp_path / "part.csv"
    assert main(["search", str(RECORDS), "--baseline", baseline, "--margin", "10", "--csv", str(full)]) == 0
    whole = pd.read_csv(full)
    visited = list(whole.loc[whole["status"].isin(["visited", "chosen"]), "cell"])
    assert visited == [f"{SPATIAL}/calib_all_a75-W4A4-e2e", f"{SPATIAL}/calib_ah-W4A4-ah"]
    prefix = _prefix(tmp_path / "prefix", RECORDS, [baseline, *visited])
    capsys.readouterr()
    assert main(["search", str(prefix), "--space", str(table), "--baseline", baseline, "--margin", "10", "--exhaustive",
                 "--csv", str(part)]) == 0
    printed = capsys.readouterr().out
    assert f"chosen: {SPATIAL}/calib_ah-W4A4-ah" in printed and "alpha 0.05 split over the 22 candidates" in printed
    assert "episodes: 350 of 4400" in printed and "recorded: 400 episodes in the 2 of 22 candidates' records" in printed
    assert "exhaustive: not decided (20 candidate(s) without records)" in printed
    part = pd.read_csv(part)
    columns = ["order", "cell", "status", "decision", "episodes_used", "delta_at_stop_pp", "delta_cs_low_pp"]
    pd.testing.assert_frame_equal(part[columns], whole[columns])
    assert set(part.loc[part["order"] > 2, "status"]) == {"not reached"}
    assert (part.loc[part["order"] > 2, "episodes_recorded"] == 0).all()


def test_a_recorded_prefix_that_does_not_determine_the_search_is_refused_naming_the_cells(tmp_path, capsys):
    """The same lattice with the cheapest candidate unrecorded (a run cut before it finished): the search would read
    it first, so it is refused, naming it and every unrecorded candidate the search may still read; nothing is
    written. Without --space the folder's 1 candidate would be the whole space: refused as a part of a larger one
    only where a live rule stopped its records (tests below)."""
    space = sorted(ref for ref in find_cells(RECORDS) if ref.startswith(SPATIAL + "/"))
    table = _space_table(tmp_path / "space.yaml", space)
    prefix = _prefix(tmp_path / "prefix", RECORDS, [f"{SPATIAL}/rtn-BASELINE-e2e", f"{SPATIAL}/calib_ah-W4A4-ah"])
    out = tmp_path / "s.csv"
    assert main(["search", str(prefix), "--space", str(table), "--margin", "10", "--csv", str(out)]) == 2
    error = capsys.readouterr().err
    assert (f"the search is not determined by the recorded candidates: it reaches {SPATIAL}/calib_all_a75-W4A4-e2e "
            "(#1 of 22 in search order), which has no finished records; the 21 candidate(s) without records it may "
            "still read: calib_all_a75-W4A4-e2e, rtn-W4A4-ah, ") in error
    assert "calib_ah-W4A4-ah," not in error and not out.exists()


def test_the_search_target_reads_the_recorded_part_of_its_space(tmp_path):
    """tables/search.csv from a records folder that lacks some of the search table's cells: the DAG plans the search
    on the recorded ones (no refusal while it is built), and its job (write_search over the whole space, what
    workflow/scripts/search_table.py runs) counts the unrecorded cell in the space (alpha / 3): at 20 pp RTN W4A8 is
    then undecided and the search would read RTN W8A8 e2e next, which it names; at 25 pp W4A8 is chosen and W8A8 is
    `not reached`; with RTN W3 e2e (between W2A2 and W4A8) unrecorded too, W3 is named."""
    from vlaquantbench.tables.search import write_search

    checkout, tables = workflow_with_tables(tmp_path)
    for link in ("results/trained_sequential", "results/trained_search"):
        (checkout / link).parent.mkdir(exist_ok=True)
        (checkout / link).symlink_to(ROOT / link)
    (checkout / "manifests").symlink_to(ROOT / "manifests")
    table = yaml.safe_load((ROOT / "config/trained_sequential/tables/trained_sequential.yaml").read_text())
    table["rows"].append({"label": "W8A8", "cell": f"{TRAINED}/rtn-W8A8-e2e", "fp": f"{TRAINED}/rtn-BASELINE-e2e"})
    (tables / "trained_sequential.yaml").write_text(yaml.safe_dump(table))
    result = subprocess.run([sys.executable, "-m", "snakemake", "-n", "--cores", "1", "tables/search.csv",
                             "--configfile", "config/trained_sequential.yaml", "config/trained_sequential_fixed.yaml",
                             "config/trained_search.yaml", "--config", f"tables_dir={tables}"],
                            cwd=checkout, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    job = result.stdout.split("rule search_table:", 1)[1].split("\n\n", 1)[0]
    assert "rtn-W2A2-e2e/episodes.parquet" in job and "rtn-W4A8-e2e/episodes.parquet" in job and "W8A8" not in job

    cells = {ref: read_cell(path) for ref, path in find_cells(TRAINED_FIXED).items()}
    baseline = f"{TRAINED}/rtn-BASELINE-e2e"
    space = [baseline, f"{TRAINED}/rtn-W2A2-e2e", f"{TRAINED}/rtn-W4A8-e2e", f"{TRAINED}/rtn-W8A8-e2e"]
    with pytest.raises(UserError, match=rf"it reaches {TRAINED}/rtn-W8A8-e2e \(#3 of 3 in search order\), which has "
                                        r"no finished records \(decided before it: rtn-W2A2-e2e worse, rtn-W4A8-e2e "
                                        r"undecided\); the 1 candidate\(s\) without records it may still read: rtn-W8A8"):
        write_search(cells, baseline, SearchDesign(0.05, 20.0), tmp_path / "t.csv", space=space)
    report = write_search(cells, baseline, SearchDesign(0.05, 25.0), tmp_path / "s.csv", space=space)
    assert report.result.chosen.ref == f"{TRAINED}/rtn-W4A8-e2e" and report.unrecorded == (f"{TRAINED}/rtn-W8A8-e2e",)
    assert report.result.status(f"{TRAINED}/rtn-W8A8-e2e") == "not reached"
    assert "alpha 0.05 split over the 3 candidates" in report.summary()[0]
    with pytest.raises(UserError, match=rf"it reaches {TRAINED}/rtn-W3-e2e \(#2 of 4 in search order\), which has no "
                                        r"finished records \(decided before it: rtn-W2A2-e2e worse\)"):
        write_search(cells, baseline, SearchDesign(0.05, 25.0), tmp_path / "t.csv", space=[*space, f"{TRAINED}/rtn-W3-e2e"])
    assert not (tmp_path / "t.csv").exists()


def test_an_unrecorded_candidate_as_costly_as_a_recorded_one_blocks_it_where_proxies_order_them():
    """Equal weight memory and activation bits are ordered by the proxy the headers give (their layer errors): where
    the space's headers give proxies, a recorded candidate ties with an unrecorded one whose proxy is still unknown,
    so the search is not determined there; where none gives one, the name orders them and the search answers."""
    gate, up = f"{SPATIAL}/ablate-W4A4-ah-only_gate", f"{SPATIAL}/ablate-W4A4-ah-only_up"
    assert Candidate.from_ref(gate).cost_bits == Candidate.from_ref(up).cost_bits

    def decide(candidate, design):
        return Verdict("not_worse", 10, 10)

    with pytest.raises(UserError, match=r"it reaches .*only_up \(#2 of 2 in search order\), which has no finished "
                                        r"records; the 1 candidate\(s\) without records it may still read: "
                                        r"ablate-W4A4-ah-only_up\."):
        precision_search([Candidate.from_ref(gate, proxy=0.1), Candidate.from_ref(up)], decide, SearchDesign(), [up])
    result = precision_search([Candidate.from_ref(gate), Candidate.from_ref(up)], decide, SearchDesign(), [up])
    assert result.chosen.ref == gate and result.status(up) == "not reached"


def test_live_records_of_a_larger_space_are_refused_naming_its_size(tmp_path, capsys):
    """Records a live rule stopped at alpha / K' searched as a space of fewer candidates (a folder holding part of the
    space, searched without --space) are refused, naming the space they were stopped for."""
    out = tmp_path / "s.csv"
    assert main(["search", str(TRAINED_LIVE), "--cells", "rtn-W2A2-e2e", "--alpha", "0.1", "--csv", str(out)]) == 2
    assert ("rtn-W2A2-e2e: its records were stopped by a live rule at alpha 0.05 = 0.1 / 2, a space of 2 candidates, "
            "and 1 are searched here") in capsys.readouterr().err
