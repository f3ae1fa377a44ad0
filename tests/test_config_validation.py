"""Every YAML kind through the one loader, and bad input refused early and by name: `vqb rollout --show`
validates a config exactly as Snakemake does, and a bad cell in a table fails `snakemake -n` naming the
table file and the cell, before any job runs (issue 14 §2, issue 17 items 1-2)."""

import dataclasses
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from vlaquantbench.config import load_workflow_config, load_yaml, schema, validate
from vlaquantbench.config.study import RunnerConfig, StudyConfig
from vlaquantbench.errors import UserError
from vlaquantbench.workflow import WorkflowConfig
from paths import ROOT

PACKAGE = ROOT / "src" / "vlaquantbench"
PAPER_STUDY = ROOT / "config" / "replay" / "pi05_libero_spatial.yaml"  # the paper's replay study
COMMITTED = {
    "config": sorted((ROOT / "config").glob("*.yaml")),
    "table": sorted((ROOT / "config").glob("**/tables/*.yaml")),  # the paper's, the demo's and each study's
    "layer_index_table": sorted((ROOT / "config" / "layer_index_tables").glob("*.yaml")),
    "figure": sorted((ROOT / "config" / "figures").glob("*.yaml")),
    "scopes": [ROOT / "config" / "scopes.yaml"],
    "cohort": sorted((ROOT / "config" / "cohorts").glob("*.yaml")),
    "replay_study": sorted((ROOT / "config" / "replay").glob("*.yaml")),
}
COMMITTED["config"].remove(ROOT / "config" / "scopes.yaml")  # the link to the package's subsets
DEMO_TABLE = ROOT / "config" / "demo" / "tables" / "lattice.yaml"
ATTENTION = "libero/libero_spatial/pi05/ablate-W4A4-ah-onlyself_attn"


@pytest.mark.parametrize("kind", sorted(COMMITTED))
def test_every_committed_yaml_satisfies_its_schema(kind):
    assert COMMITTED[kind]
    for path in COMMITTED[kind]:
        if kind == "config":  # as Snakemake reads `--configfile path`: merged over config/config.yaml
            load_workflow_config(path, ROOT / "config" / "config.yaml")
        else:
            load_yaml(path, kind)


def test_every_committed_config_defines_the_tables_it_lists():
    """`tables/<name>.tex` of a config's `tables` is built from `<tables_dir>/<name>.yaml`; a config
    pointing its definitions at the wrong folder leaves snakemake with no rule for the target."""
    for path in COMMITTED["config"]:
        raw = load_workflow_config(path, ROOT / "config" / "config.yaml")
        workflow = WorkflowConfig.from_snakemake(raw, ROOT)
        missing = sorted(set(raw.get("tables", [])) - set(workflow.table_names()))
        assert not missing, f"{path.name}: no definition of {missing} in {workflow.tables_dir}"


BROKEN = [  # (schema, file content, the field path and problem the error must name)
    ("config", {"tables": ["lattice"], "study": {"execution": {"num_env": 3}}},
     r"study.execution: unknown key 'num_env'; allowed keys: episode_order, gpus, jobs_per_gpu, num_envs, progress, torch_threads"),
    # study.runner is open beside its runner options (the env settings of any benchmark, whose declarations the
    # schema cannot list); their values are scalars
    ("config", {"tables": ["lattice"], "study": {"runner": {"camera_size": [256]}}},
     r"study.runner.camera_size: \[256\] is not of type 'integer', 'number', 'string', 'boolean', 'null'"),
    # The schema holds the only lists of runner samplers and replay options (nothing re-checks them).
    ("config", {"tables": ["lattice"], "study": {"runner": {"sampler": "fast"}}},
     r"study.runner.sampler: 'fast' is not allowed; allowed values: auto, captured, eager"),
    ("config", {"tables": ["lattice"], "replay": {"init_state": [20]}},
     r"replay: unknown key 'init_state'; allowed keys: checkpoint, checkpoint_dir, device, executed_chunk, flow_steps"),
    ("table", {"caption": "c", "align": "lr", "header": [["a"]], "values": [{"stat": "rate", "cell": "c"}],
               "rows": [{"label": "x", "c": "libero/libero_spatial/pi05/rtn-W4A4-ah"}], "enviroment": "tabular"},
     r"\(top level\): unknown key 'enviroment'; allowed keys: align, bootstrap, caption, cells, environment"),
    ("figure", {"baseline": "a/b/c/d", "isolated": [{"label": "x"}], "nested": [{"label": "y", "cell": "a/b/c/d"}]},
     r"isolated.0: 'cell' is a required property"),
    ("scopes", {"pi05": {"onlyself_attn": {"scope": "ah", "only": ["*self_attn*"], "layer": 72}}},
     r"pi05.onlyself_attn: unknown key 'layer'; allowed keys: exclude, layers, only, params, scope"),
    ("cohort", {"benchmark": "libero", "suite": "libero_spatial", "models": {}},
     r"models: {} should be non-empty"),
    ("replay_study", {**yaml.safe_load(PAPER_STUDY.read_text()), "revision": "main"},
     r"revision: 'main' does not match"),
]


@pytest.mark.parametrize(("kind", "content", "message"), BROKEN, ids=[b[0] for b in BROKEN])
def test_the_loader_names_the_file_and_the_field(tmp_path, kind, content, message):
    path = tmp_path / f"{kind}.yaml"
    path.write_text(yaml.safe_dump(content))
    with pytest.raises(UserError, match=rf"^{path}: (\s+.*\n)*?\s*{message}"):
        load_yaml(path, kind)


def test_defaults_live_in_the_dataclasses_and_the_schema_allows_exactly_their_fields():
    study = schema("config")["properties"]["study"]
    def keys(node):
        if isinstance(node, dict):
            yield from node
            for value in node.values():
                yield from keys(value)
        elif isinstance(node, list):
            for value in node:
                yield from keys(value)

    assert "default" not in set(keys(schema("config")))  # Snakemake's validate would fill them in
    # every field but those derived from others (which keys study.runner names) is a config key
    assert set(study["properties"]) == {f.name for f in dataclasses.fields(StudyConfig) if "derived" not in f.metadata}
    assert set(study["properties"]["runner"]["properties"]) == {f.name for f in dataclasses.fields(RunnerConfig)}
    # The Snakefile validates with the same file: workflow/schemas links to the package's schema.
    assert (ROOT / "workflow/schemas/config.schema.yaml").resolve() == (PACKAGE / "config/schemas/config.schema.yaml")
    assert StudyConfig.from_dict({}).runner == RunnerConfig() and StudyConfig.from_dict({}).episodes_per_task is None  # each model's client
    with pytest.raises(UserError, match=r"^where: study.tasks: 0 is not valid"):
        validate({"tasks": 0}, "config", "where", subschema=("study",))


# --- vqb rollout CELL --config FILE --show: the real command line ---


def vqb_show(config: Path, ref: str = ATTENTION) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "vlaquantbench.cli", "rollout", ref, "--config", str(config), "--show",
           "--results", str(config.parent / "out")]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=120, cwd=ROOT)


def demo_config(tmp_path: Path, edit) -> Path:
    config = yaml.safe_load((ROOT / "config" / "config.yaml").read_text())
    edit(config)
    path = tmp_path / "config.yaml"
    path.write_text(yaml.safe_dump(config))
    return path


MISSPELT = [
    (lambda c: c["study"].update(episodes_per_tsak=2), "study: unknown key 'episodes_per_tsak'; allowed keys: allocations, calibration, episodes_per_task"),
    # no registered benchmark's env setting either: refused as the schema refuses a misspelt key
    (lambda c: c["study"]["runner"].update(max_step=3), "study.runner: unknown key 'max_step'; allowed keys: device, dtype, "
                                                        "executed_chunk, flow_steps, max_steps, sampler, and a benchmark's "
                                                        "env settings (libero: camera_size, settle_steps"),
    (lambda c: c["study"]["models"]["pi05"].update(varient="full"), "study.models.pi05: unknown key 'varient'; allowed keys: checkpoint, episodes_per_task, revision, runner, trained, variant"),
    (lambda c: c.update(stduy={}), r"\(top level\): unknown key 'stduy'; allowed keys: demonstrations, diagnostics_dir, manifest"),
    (lambda c: c["study"].update(episodes_per_task=0), "study.episodes_per_task: 0 is less than the minimum of 1"),
    (lambda c: c["study"]["models"]["pi05"].update(variant="ful"), "study.models.pi05.variant: 'ful' is not allowed; allowed values: full, demo, random"),
]


@pytest.mark.parametrize(("edit", "message"), MISSPELT, ids=["episodes", "max_step", "variant_key", "top_level", "zero", "variant_value"])
def test_vqb_rollout_refuses_a_bad_config_before_anything_runs(tmp_path, edit, message):
    config = demo_config(tmp_path, edit)
    result = vqb_show(config)
    assert result.returncode == 2, result.stdout
    assert f"vqb rollout: error: {config} (merged over config/config.yaml): " in result.stderr, result.stderr
    assert message.replace("\\", "") in result.stderr.replace("\\", ""), result.stderr
    assert not (tmp_path / "out").exists()


def test_vqb_rollout_show_names_the_folder_snakemake_uses(tmp_path):
    config = demo_config(tmp_path, lambda c: None)
    result = vqb_show(config)
    assert result.returncode == 0, result.stderr
    wf = WorkflowConfig.from_snakemake(yaml.safe_load(config.read_text()), ROOT)
    shown = yaml.safe_load(result.stdout)
    assert shown["config_hash"] in wf.study_cells() and wf.study_cells()[shown["config_hash"]] == shown["config"]


# --- snakemake -n: a bad cell of a table is refused while the DAG is built ---


def dry_run(tmp_path: Path, row_cell: str | None = None, copy_src: bool = False, study_edit=None) -> tuple[int, str]:
    """`snakemake -n tables/lattice.tex` on the demo study in a checkout whose demo lattice table has one
    row, reading `row_cell`."""
    checkout = tmp_path / "checkout"
    checkout.mkdir()
    for item in ("Snakefile", "rules", "workflow", "manifests"):
        (checkout / item).symlink_to(ROOT / item)
    shutil.copytree(ROOT / "config", checkout / "config", symlinks=True)
    if copy_src:
        shutil.copytree(ROOT / "src", checkout / "src", ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
        (checkout / "config" / "scopes.yaml").unlink()
        (checkout / "config" / "scopes.yaml").symlink_to(checkout / "src/vlaquantbench/config/scopes.yaml")
    else:
        (checkout / "src").symlink_to(ROOT / "src")
    table_path = checkout / "config" / "demo" / "tables" / "lattice.yaml"
    table = yaml.safe_load(table_path.read_text())
    table["rows"] = [{"label": "row", "cell": row_cell or ATTENTION}]
    table_path.write_text(yaml.safe_dump(table))
    if study_edit:
        config_path = checkout / "config" / "config.yaml"
        config = yaml.safe_load(config_path.read_text())
        study_edit(config)
        config_path.write_text(yaml.safe_dump(config))
    cmd = [sys.executable, "-m", "snakemake", "-n", "tables/lattice.tex", "--cores", "1", "--configfile=config/config.yaml"]
    result = subprocess.run(cmd, cwd=checkout, capture_output=True, text=True, timeout=300)
    return result.returncode, result.stdout + result.stderr


BAD_CELLS = [
    ("libero/libero_spatail/pi05/rtn-W4A4-ah", "unknown libero suite 'libero_spatail'; known: libero_spatial"),
    ("libero/libero_spatial/pi5/rtn-W4A4-ah", "unknown model 'pi5'; known: metaworld_expert, openvla_oft, pi0, pi05, xvla"),
    ("libero/libero_spatial/pi05/rtn-W4A3X-ah", "unknown quantization preset 'W4A3X'"),
    ("libero/libero_spatial/pi05/quip-W4A4-ah", "unknown method 'quip'; expected one of awq, fp8, fp8_static"),
    ("libero/libero_spatial/pi05/ablate-W4A4-ah-onlyselfattn", "subset 'onlyselfattn' of pi05: unknown subset 'onlyselfattn'"),
    ("metaworld/metaworld_eazy/metaworld_expert/rtn-BASELINE-e2e",
     "unknown metaworld suite 'metaworld_eazy'; known: metaworld_easy, metaworld_medium"),
    ("metaworlds/metaworld_easy/metaworld_expert/rtn-BASELINE-e2e", "unknown benchmark 'metaworlds'; known: libero, metaworld"),
]


@pytest.mark.parametrize(("cell", "message"), BAD_CELLS,
                         ids=["suite", "model", "preset", "method", "subset", "metaworld_suite", "benchmark"])
def test_snakemake_dry_run_refuses_a_bad_cell_naming_the_table_and_the_cell(tmp_path, cell, message):
    returncode, output = dry_run(tmp_path, cell)
    table = tmp_path / "checkout/config/demo/tables/lattice.yaml"
    assert returncode != 0 and f"{table}: cell {cell!r}: {message}" in output, output[-3000:]


def test_snakemake_dry_run_refuses_a_subset_pattern_that_matches_nothing(tmp_path):
    def misspell_pattern(_):
        scopes = tmp_path / "checkout/src/vlaquantbench/config/scopes.yaml"
        scopes.write_text(scopes.read_text().replace('onlyself_attn: {scope: ah, only: ["*self_attn*"]',
                                                     'onlyself_attn: {scope: ah, only: ["*self_atn*"]'))

    returncode, output = dry_run(tmp_path, copy_src=True, study_edit=misspell_pattern)
    table = tmp_path / "checkout/config/demo/tables/lattice.yaml"
    assert returncode != 0 and (f"{table}: cell {ATTENTION!r}: subset 'onlyself_attn' of pi05: pattern --only "
                                "'*self_atn*' matches no linear layer in scope 'ah'") in output, output[-3000:]


def test_snakemake_validates_the_same_schema(tmp_path):
    returncode, output = dry_run(tmp_path, study_edit=lambda c: c["study"].setdefault("execution", {}).update(num_env=3))
    assert returncode != 0 and "'num_env' was unexpected" in output, output[-3000:]


def test_replay_configurations_take_subsets_from_scopes_yaml(tmp_path):
    from vlaquantbench.replay.study import load_study
    from vlaquantbench.quant.subsets import get_subset

    study = load_study(PAPER_STUDY)
    assert study["configurations"]["union"]["layers"] == get_subset("pi05", "attn_adarms").layers == 108
    text = PAPER_STUDY.read_text()
    path = tmp_path / "study.yaml"
    path.write_text(text.replace("subset: attn_adarms,", "subset: attn_adarms, layers: 108,"))
    with pytest.raises(UserError, match=rf"^{path}: configurations.union: .* should not be valid"):
        load_study(path)  # a subset's layer count lives in config/scopes.yaml only
    path.write_text(text.replace("subset: attn_adarms,", "subset: attn_adarm,"))
    with pytest.raises(UserError, match=r"configurations.union.subset: unknown subset 'attn_adarm' for model 'pi05'"):
        load_study(path)


# --- issue 35 item 4: what needs no simulator is checked by `vqb rollout --show` and `snakemake -n` ---

CALIBRATED = "libero/libero_spatial/pi05/calib_set20_ah-W4A4-ah"
OUTSIDE_THE_SUITE = [  # (study edit, cell, the field, value and range the error must name)
    (lambda s: s.update(tasks=[99]), ATTENTION, "study.tasks: 99 is outside 0..9 (libero_spatial has 10 tasks)"),
    (lambda s: s.update(tasks=12), ATTENTION, "study.tasks: 12 tasks, but libero_spatial has 10 (task ids 0..9)"),
    (lambda s: s.update(episodes_per_task=51), ATTENTION,
     "study.episodes_per_task: 51 episodes per task, but libero_spatial has 50 official init states per task"),
    (lambda s: None, CALIBRATED, "calibration init states (study.calibration.first_init_state 20 + 2 x calib_set 20, "
                                 "study.calibration.episodes 2): 60, 61 are outside 0..49"),
    (lambda s: s.setdefault("calibration", {}).update(tasks=11), "libero/libero_spatial/pi05/calib_ah-W4A4-ah",
     "study.calibration.tasks: 11 tasks, but libero_spatial has 10"),
    (lambda s: s["runner"].update(mujoco="3.4.0"), ATTENTION,
     "study.runner.mujoco: '3.4.0', but pi05 cells run on MuJoCo 3.3.2"),
]
OUTSIDE_IDS = ["task_id", "task_count", "episodes", "calibration_init_states", "calibration_tasks", "mujoco"]


@pytest.mark.parametrize(("edit", "cell", "message"), OUTSIDE_THE_SUITE, ids=OUTSIDE_IDS)
def test_vqb_rollout_show_refuses_what_the_suite_does_not_have(tmp_path, edit, cell, message):
    config = demo_config(tmp_path, lambda c: edit(c["study"]))
    result = vqb_show(config, cell)
    assert result.returncode == 2 and f"vqb rollout: error: cell {cell!r}: {message}" in result.stderr, result.stderr
    assert not (tmp_path / "out").exists()


def test_snakemake_dry_run_refuses_task_ids_outside_the_suite(tmp_path):
    returncode, output = dry_run(tmp_path, study_edit=lambda c: c["study"].update(tasks=[99]))
    table = tmp_path / "checkout/config/demo/tables/lattice.yaml"
    assert returncode != 0 and (f"{table}: cell {ATTENTION!r}: study.tasks: 99 is outside 0..9 "
                                "(libero_spatial has 10 tasks)") in output, output[-3000:]


def test_replay_trajectories_outside_the_suite_are_refused_while_the_dag_is_built():
    from vlaquantbench.replay.study import RecordSettings, load_study

    with pytest.raises(UserError, match=r"^replay.init_states: 50 is outside 0..49 \(libero_spatial has 50 official init "):
        RecordSettings.from_study(load_study(PAPER_STUDY), {"init_states": [20, 50]})
    with pytest.raises(UserError, match=r"^replay.tasks: 10, 11 are outside 0..9 \(libero_spatial has 10 tasks\)"):
        RecordSettings.from_study(load_study(PAPER_STUDY), {"tasks": [9, 10, 11]})


def test_a_replay_study_setting_an_env_setting_its_benchmark_does_not_take_is_refused(tmp_path):
    """A replay study's `runner` is its cells' env settings: one its benchmark does not declare (Meta-World has no
    settle steps) would go unused by the recording's env, so loading the study refuses it, naming the field."""
    from vlaquantbench.replay.study import load_study

    study = tmp_path / "metaworld_study.yaml"
    study.write_text(yaml.safe_dump({**yaml.safe_load(PAPER_STUDY.read_text()), "benchmark": "metaworld",
                                     "suite": "metaworld_mt50", "runner": {"camera_size": 64, "settle_steps": 5}}))
    with pytest.raises(UserError, match=rf"^replay study {re.escape(repr(str(study)))}: runner.settle_steps: "
                                        r"'settle_steps' is not an env setting of metaworld \(it takes camera_size, mujoco"):
        load_study(study)
    assert load_study(PAPER_STUDY)["runner"] == {}  # the paper's LIBERO cells render at LIBERO's defaults


CLI_NUMBERS = [  # every numeric option of `vqb`: (arguments, the option and range argparse names)
    (["rollout", ATTENTION, "--show", "--num-envs", "0"], "vqb rollout: error: argument --num-envs: 0 is less than the minimum of 1"),
    (["rollout", ATTENTION, "--show", "--num-envs", "-3"], "argument --num-envs: -3 is less than the minimum of 1"),
    (["rollout", ATTENTION, "--show", "--num-envs", "2.5"], "argument --num-envs: '2.5' is not an integer"),
    (["hub-fixture", "unused", "--seed", "-1"], "vqb hub-fixture: error: argument --seed: -1 is less than the minimum of 0"),
]


@pytest.mark.parametrize(("arguments", "message"), CLI_NUMBERS, ids=["num_envs_0", "num_envs_negative", "num_envs_float", "seed"])
def test_vqb_refuses_numbers_out_of_range_naming_the_option(tmp_path, arguments, message):
    result = subprocess.run([sys.executable, "-m", "vlaquantbench.cli", *arguments], capture_output=True, text=True,
                            timeout=120, cwd=tmp_path)
    assert result.returncode == 2 and message in result.stderr, result.stderr
    assert list(tmp_path.iterdir()) == []
