"""What a cell's folder and resume check cover: results-changing fields and the quantization-semantics
version, not the code revision nor the cell's name."""

import pytest

from vlaquantbench import cells
from vlaquantbench.cells import CellConfig, cell_config, config_hash
from vlaquantbench.envs.registry import get_benchmark
from vlaquantbench.errors import UserError
from vlaquantbench.quant.semantics import QUANT_SEMANTICS
from vlaquantbench.runner.journal import CellJournal

STUDY = {"models": {"pi05": {"variant": "demo"}}, "tasks": 1, "episodes_per_task": 2}
RTN, ABLATE = "libero/libero_spatial/pi05/rtn-W4A4-ah", "libero/libero_spatial/pi05/ablate-W4A4-ah"
EPISODE = {"suite": "libero_spatial", "task_id": 0, "episode": 0, "seed": 0, "init_state_id": 0, "success": False,
           "steps": 30}  # fmt: skip


def header(ref, **changes):
    cfg = cell_config(ref, STUDY)
    return {"config_hash": config_hash(cfg), "ref": ref, "cell": cfg["cell"], "method": cfg["method"], "config": cfg,
            **{k: cfg[k] for k in ("model", "benchmark", "suite", "seed", "episodes_per_task")},  # as runner.cell writes them
            "quant_semantics": QUANT_SEMANTICS, "code_revision": "1a2b3c4", **changes}  # fmt: skip


def test_one_experiment_under_two_names_is_one_folder():
    # One folder, hence one rollout job: the workflow keys its cells by this hash (WorkflowConfig.study_cells).
    assert config_hash(cell_config(RTN, STUDY)) == config_hash(cell_config(ABLATE, STUDY))
    other = ["libero/libero_spatial/pi05/calib_ah-W4A4-ah", "libero/libero_spatial/pi05/rtn-W4A8-ah"]
    assert len({config_hash(cell_config(ref, STUDY)) for ref in [RTN, *other]}) == 3


def test_a_cell_holds_and_hashes_only_the_env_settings_its_benchmark_declares():
    """Meta-World takes no settle steps and no controller mode: its cells hold neither (typed: its own settings
    dataclass, with its own defaults), so no value of theirs can split a folder; a LIBERO cell holds all four of
    LIBERO's settings, its 256 px camera LIBERO's declared default."""
    metaworld = cell_config("metaworld/metaworld_mt50/metaworld_expert/rtn-BASELINE-e2e",
                            {"models": {"metaworld_expert": {"variant": "full"}}, "tasks": 1})
    env = {"camera_size", "settle_steps", "control_mode", "mujoco"}
    assert env & set(metaworld["runner"]) == {"camera_size", "mujoco"} and metaworld["runner"]["camera_size"] == 480
    libero = cell_config(RTN, {**STUDY, "runner": {}})
    assert env <= set(libero["runner"]) and libero["runner"]["camera_size"] == 256
    typed = CellConfig.from_dict(metaworld)
    assert typed.env == get_benchmark("metaworld").settings(camera_size=480, mujoco="3.3.2")
    assert typed.to_dict() == metaworld
    # a header written before (both settings in its runner) reads back into the same cell
    before = {**metaworld, "runner": {**metaworld["runner"], "settle_steps": 10, "control_mode": "delta"}}
    assert config_hash(before) != config_hash(metaworld) and CellConfig.from_dict(before).to_dict() == metaworld


def test_the_semantics_version_enters_every_hash(monkeypatch):
    before = config_hash(cell_config(RTN, STUDY))
    monkeypatch.setattr(cells, "QUANT_SEMANTICS", QUANT_SEMANTICS + 1)
    assert config_hash(cell_config(RTN, STUDY)) != before


def test_a_killed_cell_resumes_after_a_commit_and_under_its_other_name(tmp_path):
    path = tmp_path / "journal.jsonl"
    CellJournal(path, header(RTN)).record([EPISODE], fired=set())
    resumed = CellJournal(path, header(ABLATE, code_revision="9f8e7d6-dirty"))
    assert resumed.done_keys() == {(0, 0, 0)}


def test_a_killed_cell_is_not_resumed_by_other_quantization_semantics(tmp_path):
    path = tmp_path / "journal.jsonl"
    CellJournal(path, header(RTN)).record([EPISODE], fired=set())
    with pytest.raises(UserError, match=f"quant_semantics: recorded={QUANT_SEMANTICS} current={QUANT_SEMANTICS + 1}"):
        CellJournal(path, header(RTN, quant_semantics=QUANT_SEMANTICS + 1))


def test_a_resumed_cell_may_measure_its_fast_path_probe_anew_but_not_change_its_bound(tmp_path):
    path = tmp_path / "journal.jsonl"
    probe = {"path": "captured", "device": "cuda", "max_abs_diff": 0.012, "rel_l2": 3.1e-3, "bound": 0.05, "passed": True}
    CellJournal(path, header(RTN, inference={"sampler": "captured", "fast_path_probe": probe})).record([EPISODE], fired=set())
    remeasured = {**probe, "max_abs_diff": 0.013, "rel_l2": 3.4e-3}
    resumed = CellJournal(path, header(RTN, inference={"sampler": "captured", "fast_path_probe": remeasured}))
    assert resumed.done_keys() == {(0, 0, 0)}
    with pytest.raises(UserError, match="inference: recorded="):
        CellJournal(path, header(RTN, inference={"sampler": "captured", "fast_path_probe": {**probe, "bound": 0.1}}))


# --- Named allocations (issue 52): `alloc-<name>` is the cell study.allocations names, under another name ---
SPELLED = "ablate-W4A4-ah-onlyself_attn"
ALLOCATED = {**STUDY, "allocations": {"chosen": SPELLED, "other": "rtn-W4A8-ah"}}


@pytest.mark.parametrize("prefix", ["", "seed1-", "steps5-", "seed2-steps3-"])
def test_a_named_allocation_is_the_cell_it_names(prefix):
    """The same canonical config but for its names, hence one hash, one folder, one job; the allocations enter
    no other cell's hash."""
    named = cell_config(f"libero/libero_spatial/pi05/{prefix}alloc-chosen", ALLOCATED)
    spelled = cell_config(f"libero/libero_spatial/pi05/{prefix}{SPELLED}", STUDY)
    assert config_hash(named) == config_hash(spelled)
    assert {key for key in named if named[key] != spelled[key]} == {"ref", "cell"}
    assert named["cell"] == f"{prefix}alloc-chosen" and named["only"] == spelled["only"] and named["only"]
    assert config_hash(cell_config(f"libero/libero_spatial/pi05/{prefix}{SPELLED}", ALLOCATED)) == config_hash(spelled)
    other = cell_config(f"libero/libero_spatial/pi05/{prefix}alloc-other", ALLOCATED)
    assert (other["method"], other["preset"], other["scope"], other["only"]) == ("rtn", "W4A8", "ah", None)
    assert config_hash(other) != config_hash(named)


@pytest.mark.parametrize("study, ref, message", [
    (ALLOCATED, "alloc-chosn", "unknown allocation 'chosn': study.allocations defines chosen, other"),
    (STUDY, "alloc-chosen", "unknown allocation 'chosen': study.allocations defines none"),
    ({**STUDY, "allocations": {"chosen": "steps5-rtn-W4-e2e"}}, "steps3-alloc-chosen",
     "allocation 'chosen' is steps5-rtn-W4-e2e, which sets the flow steps already"),
    ({**STUDY, "allocations": {"chosen": "rtn-W4-e2e-nosuch"}}, "alloc-chosen", "subset 'nosuch'"),
])
def test_a_bad_named_allocation_is_refused_naming_it(study, ref, message):
    with pytest.raises(UserError, match=f"cell 'libero/libero_spatial/pi05/{ref}'.*{message}"):
        cell_config(f"libero/libero_spatial/pi05/{ref}", study)


def test_an_allocation_is_a_cell_name_and_resolves_only_with_its_study():
    with pytest.raises(UserError, match=r"study.allocations.chosen: 'seed1-rtn-W4-e2e' does not match"):
        cell_config("libero/libero_spatial/pi05/alloc-chosen", {**STUDY, "allocations": {"chosen": "seed1-rtn-W4-e2e"}})
    with pytest.raises(UserError, match="'alloc-chosen' names an allocation of study.allocations, which only a study's"):
        cells.quantized_counts("libero/libero_spatial/pi05/alloc-chosen")
