"""Bad input to the parts added for Meta-World, demonstrations, training and sequential evaluation (issue 48) is
refused before any expensive work, by name: step limits beyond the simulator's, demonstrations on evaluated
variations. Real Meta-World and LIBERO give the limits; the workflow refusals are real `snakemake -n` runs on
the committed trained-policy config (config/trained_cpu.yaml)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from paths import ROOT
from vlaquantbench.cells import cell_config
from vlaquantbench.config.study import StudyConfig
from vlaquantbench.demonstrations import DemonstrationConfig, check_disjoint_from_evaluation
from vlaquantbench.envs import BENCHMARK_SUITES
from vlaquantbench.errors import UserError

TRAINED_CPU = "config/trained_cpu.yaml"
DEMONSTRATED = {"benchmark": "metaworld", "tasks": ["drawer-close-v3"]}  # a demonstrations section


def checkout_with_records(tmp_path: Path) -> Path:
    """A working folder that links the workflow, the package, the committed checkpoints, manifests and
    records (a dry run writes only its own .snakemake/ here)."""
    checkout = tmp_path / "checkout"
    (checkout / "results").mkdir(parents=True)
    for item in ("Snakefile", "rules", "workflow", "config", "src", "checkpoints", "manifests"):
        (checkout / item).symlink_to(ROOT / item)
    for records in (ROOT / "results").iterdir():
        if records.is_dir():
            (checkout / "results" / records.name).symlink_to(records)
    return checkout


def dry_run(checkout: Path, target: str, overrides: dict, *config: str) -> tuple[int, str]:
    """`snakemake -n target --configfile config/trained_cpu.yaml <overrides>` [--config ...]: its exit status and
    output (Snakemake prints a parse-time error on stdout, a job plan on stdout, its own messages on stderr)."""
    (checkout / "overrides.yaml").write_text(yaml.safe_dump(overrides))
    run = subprocess.run([sys.executable, "-m", "snakemake", "-n", target, "--configfile", TRAINED_CPU,
                          "overrides.yaml", *(("--config", *config) if config else ())],
                         cwd=checkout, capture_output=True, text=True, timeout=600)
    return run.returncode, run.stdout + run.stderr


# --- 1. Step limits: each benchmark's hard limit, refused by field while the DAG is built ----------------


def test_the_declared_horizons_are_the_simulators_own():
    import inspect

    from metaworld.env_dict import ALL_V3_ENVIRONMENTS

    from vlaquantbench.envs.libero.offline import load_libero

    load_libero()  # LIBERO's own paths, without its interactive first-run prompt
    from libero.libero.envs.env_wrapper import ControlEnv

    assert BENCHMARK_SUITES["metaworld"]["metaworld_mt50"].horizon.steps == ALL_V3_ENVIRONMENTS["reach-v3"]().max_path_length
    assert BENCHMARK_SUITES["libero"]["libero_10"].horizon.steps == inspect.signature(ControlEnv).parameters["horizon"].default


@pytest.mark.parametrize(("ref", "study", "message"), [
    ("metaworld/metaworld_mt50/metaworld_expert/rtn-BASELINE-e2e",
     {"models": {"metaworld_expert": {"variant": "full"}}, "tasks": 1, "episodes_per_task": 1, "runner": {"max_steps": 501}},
     r"study\.runner\.max_steps: 501 steps is beyond metaworld_mt50's limit of 500 env steps an episode "
     r"\(Meta-World's max_path_length: it refuses to step on\); set it to at most 500"),
    ("libero/libero_spatial/pi05/rtn-BASELINE-e2e",
     {"models": {"pi05": {"variant": "demo", "runner": {"max_steps": 995}}}, "tasks": 1, "episodes_per_task": 1},
     r"study\.models\.pi05\.runner\.max_steps: 995 steps after libero's default settle_steps 10 is beyond "
     r"libero_spatial's limit of 1000 env steps .*; set it to at most 990"),
])
def test_a_cell_stepping_past_the_simulators_limit_is_refused_naming_the_field(ref, study, message):
    with pytest.raises(UserError, match=message):
        cell_config(ref, study)
    # settle steps are LIBERO's env setting only: a Meta-World cell is refused one (test below)
    at_the_limit = {**study, "runner": {"max_steps": 500, **({"settle_steps": 0} if ref.startswith("libero/") else {})}}
    at_the_limit["models"] = {model: {"variant": w["variant"]} for model, w in study["models"].items()}
    assert cell_config(ref, at_the_limit)["runner"]["max_steps"] == 500


def test_demonstrations_stepping_past_meta_worlds_limit_are_refused_naming_the_field():
    with pytest.raises(UserError, match=r"^demonstrations\.max_steps: 600 steps is beyond metaworld_mt50's limit of 500"):
        DemonstrationConfig.from_dict({**DEMONSTRATED, "max_steps": 600})
    with pytest.raises(UserError, match=r"unknown metaworld suite \(demonstrations\.suite\) 'mt50'"):
        DemonstrationConfig.from_dict({**DEMONSTRATED, "suite": "mt50"})
    assert DemonstrationConfig.from_dict({**DEMONSTRATED, "max_steps": 500}).max_steps == 500


def test_demonstrations_of_a_benchmark_without_a_scripted_expert_are_refused_naming_the_field():
    """LIBERO declares no scripted expert: a section naming it is refused as it is read, from the light
    declarations alone (a fresh interpreter imports no simulator on the way); so is an unknown benchmark."""
    code = ("import sys\n"
            "from vlaquantbench.demonstrations import DemonstrationConfig\n"
            "try:\n"
            "    DemonstrationConfig.from_dict({'benchmark': 'libero', 'tasks': ['pick_up_the_black_bowl']})\n"
            "except Exception as err:\n"
            "    print(type(err).__name__, err)\n"
            "print([m for m in ('libero.libero', 'robosuite', 'metaworld', 'mujoco', 'lerobot') if m in sys.modules])")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env={"PYTHONPATH": str(ROOT / "src")}).stdout
    assert out.splitlines() == ["UserError demonstrations.benchmark: libero declares no scripted expert to record "
                                "demonstrations from (benchmarks with one: metaworld)", "[]"]
    with pytest.raises(UserError, match=r"^unknown benchmark \(demonstrations\.benchmark\) 'mujoco'; known: libero, "
                                        r"metaworld$"):
        DemonstrationConfig.from_dict({**DEMONSTRATED, "benchmark": "mujoco"})


def test_the_dag_refuses_a_meta_world_study_stepping_past_500(tmp_path):
    checkout = checkout_with_records(tmp_path)
    status, output = dry_run(checkout, "tables/methods_2026.tex", {"study": {"runner": {"max_steps": 600}}},
                             "records_dir=", "manifest=")
    assert status != 0
    assert ("cell 'metaworld/metaworld_mt50/pi05/gptq-W2A2-e2e': study.runner.max_steps: 600 steps is beyond "
            "metaworld_mt50's limit of 500 env steps an episode") in output, output[-3000:]
    status, output = dry_run(checkout, "results/demonstrations/metaworld_cpu/manifest.tsv",
                             {"demonstrations": {"max_steps": 600}})
    assert status != 0 and "demonstrations.max_steps: 600 steps is beyond metaworld_mt50's limit" in output


# --- 2b. Env settings: a setting the cell's benchmark does not declare is refused by field, not dropped ------

MT50_EXPERT = "metaworld/metaworld_mt50/metaworld_expert/rtn-BASELINE-e2e"


@pytest.mark.parametrize(("study", "message"), [
    ({"models": {"metaworld_expert": {"variant": "full"}}, "tasks": 1, "runner": {"settle_steps": 10}},
     r"^cell '{ref}': study\.runner\.settle_steps: 'settle_steps' is not an env setting of metaworld \(it takes "
     r"camera_size, mujoco; settle_steps is libero's\); remove it, or set it under study\.models\.<model>\.runner "
     r"for the models whose cells run on libero only$"),
    ({"models": {"metaworld_expert": {"variant": "full", "runner": {"control_mode": "delta"}}}, "tasks": 1},
     r"^cell '{ref}': study\.models\.metaworld_expert\.runner\.control_mode: 'control_mode' is not an env setting of "
     r"metaworld \(it takes camera_size, mujoco; control_mode is libero's\); remove it$"),
])
def test_an_env_setting_the_benchmark_does_not_declare_is_refused_naming_field_and_benchmark(study, message):
    with pytest.raises(UserError, match=message.replace("{ref}", MT50_EXPERT.replace("/", "/"))):
        cell_config(MT50_EXPERT, study)
    # the settings Meta-World declares, and the policy's runner options, pass; so does LIBERO's settle_steps on LIBERO
    taken = {"models": {"metaworld_expert": {"variant": "full"}}, "tasks": 1,
             "runner": {"camera_size": 64, "device": "cpu", "max_steps": 20}}
    assert cell_config(MT50_EXPERT, taken)["runner"]["camera_size"] == 64
    libero = {"models": {"pi05": {"variant": "demo", "runner": {"control_mode": "delta"}}}, "tasks": 1,
              "runner": {"settle_steps": 3}}
    assert cell_config("libero/libero_spatial/pi05/rtn-BASELINE-e2e", libero)["runner"]["settle_steps"] == 3


def test_the_dag_refuses_a_meta_world_study_setting_settle_steps(tmp_path):
    """Before this check `settle_steps` was hashed into a Meta-World cell and never reached its env."""
    status, output = dry_run(checkout_with_records(tmp_path), "tables/methods_2026.tex",
                             {"study": {"runner": {"settle_steps": 5}}}, "records_dir=", "manifest=")
    assert status != 0
    assert ("/methods_2026.yaml: cell 'metaworld/metaworld_mt50/pi05/" in output
            and "study.runner.settle_steps: 'settle_steps' is not an env setting of metaworld" in output), output[-3000:]


# --- 3. Demonstrations on evaluated variations: every range the config names, by the range that meets ------


def test_the_readme_retrain_command_refuses_demonstrations_on_the_evaluated_variations(tmp_path):
    """config/trained_cpu.yaml reads its records (no cell in the DAG): the check runs all the same."""
    status, output = dry_run(checkout_with_records(tmp_path), "checkpoints/pi05_metaworld_cpu/training.json",
                             {"demonstrations": {"first_variation": 5}})
    assert status != 0
    assert ("the demonstrations' variations 5..44 (demonstrations.first_variation 5, max_attempts_per_task 40) meet "
            "the variations 0..9 (study.episodes_per_task 10: evaluation episode e starts from variation e) at 5..9"
            ) in output, output[-3000:]


def test_demonstrations_between_the_evaluated_and_the_calibration_variations_are_planned(tmp_path):
    """Variations 10..49: above the evaluated 0..9, below the calibration's 400, with the cells in the DAG."""
    status, output = dry_run(checkout_with_records(tmp_path), "results/demonstrations/metaworld_cpu/manifest.tsv",
                             {"demonstrations": {"first_variation": 10}}, "records_dir=", "manifest=")
    assert status == 0, output[-3000:]
    assert "rule demonstrations:" in output


def test_the_refusal_names_the_calibration_range_that_meets():
    config = yaml.safe_load((ROOT / TRAINED_CPU).read_text())
    study = StudyConfig.from_dict(config["study"])
    reaching = DemonstrationConfig.from_dict({**config["demonstrations"], "first_variation": 361})  # 361..400
    with pytest.raises(UserError, match=r"meet the variations 400\.\.400 \(study\.calibration\.first_init_state 400, "
                                        r"episodes 1\) at 400\.\.400"):
        check_disjoint_from_evaluation(reaching, study)
    check_disjoint_from_evaluation(DemonstrationConfig.from_dict({**config["demonstrations"], "first_variation": 360}), study)
    # A calib_set<k> cell calibrates 2k variations further on: only the cells in the DAG say which.
    shifted = cell_config("metaworld/metaworld_mt50/pi05/calib_set1_ah-W4A4-ah", config["study"])
    with pytest.raises(UserError, match=r"meet the variations 402\.\.402 \(cell metaworld/metaworld_mt50/pi05/"
                                        r"calib_set1_ah-W4A4-ah's calibration episodes\)"):
        check_disjoint_from_evaluation(DemonstrationConfig.from_dict({**config["demonstrations"], "first_variation": 401}),
                                       study, [shifted])


# --- 4. Record identity: an episode's task name and placement are the ones its task, seed and index determine --

METHODS_RECORDS = ROOT / "results" / "methods_2026"
BASELINE_CELL = "metaworld/metaworld_mt50/pi05/rtn-BASELINE-e2e"


def records_with_changed_episode(tmp_path: Path, row: int, change) -> Path:
    """A copy of the committed methods_2026 records whose baseline cell's episode `row` is changed by `change`
    (a function of the episodes table and the row); the records folder."""
    import shutil

    import pandas as pd

    records = tmp_path / "methods_2026"
    shutil.copytree(METHODS_RECORDS, records)
    episodes_file = records / BASELINE_CELL / "episodes.parquet"
    episodes = pd.read_parquet(episodes_file)
    change(episodes, row)
    episodes.to_parquet(episodes_file, index=False)
    return records


@pytest.mark.slow
def test_a_table_refuses_an_episode_named_after_another_task(tmp_path):
    """Row 13 is task 18 (drawer-close-v3), episode 2: named handle-press-v3 it would move to that task's row."""
    from vlaquantbench.manifest import sha256_file

    def rename(episodes, row):
        assert (episodes.at[row, "task_id"], episodes.at[row, "task_name"]) == (18, "drawer-close-v3")
        episodes.at[row, "task_name"] = "handle-press-v3"

    records = records_with_changed_episode(tmp_path, 12, rename)
    recorded = sha256_file(records / BASELINE_CELL / "episodes.parquet")
    checkout = checkout_with_records(tmp_path)
    run = subprocess.run([sys.executable, "-m", "snakemake", "--cores", "1", "tables/methods_2026.tex", "--configfile",
                          TRAINED_CPU, "--config", f"records_dir={records}", "manifest="],
                         cwd=checkout, capture_output=True, text=True, timeout=600)
    output = run.stdout + run.stderr
    assert run.returncode != 0
    assert (f"{records / BASELINE_CELL / 'episodes.parquet'} row 13 (task 18, episode 2, seed 18164): task_name: "
            "'handle-press-v3' is not task 18 of metaworld_mt50, 'drawer-close-v3'") in output, output[-3000:]
    assert not (checkout / "tables" / "methods_2026.tex").exists()
    assert sha256_file(records / BASELINE_CELL / "episodes.parquet") == recorded  # the refusal changed no record


@pytest.mark.parametrize(("change", "recorded"), [
    (lambda episodes, row: episodes.__setitem__("task_variation", [
        episodes.at[row - 1, "task_variation"] if i == row else v for i, v in enumerate(episodes["task_variation"])]),
     r"\[0\.0999, 0\.9000, 0\.0000\]"),  # episode 1's placement
    (lambda episodes, row: episodes.__setitem__("task_variation", [
        [-x for x in v] if i == row else v for i, v in enumerate(episodes["task_variation"])]),
     r"\[-0\.0861, -0\.9000, -0\.0000\]"),
])
def test_a_placement_other_than_the_one_its_episode_draws_is_refused(tmp_path, change, recorded):
    from vlaquantbench.records import read_cell

    read_cell(METHODS_RECORDS / BASELINE_CELL)  # as recorded: every placement is the one Meta-World draws
    records = records_with_changed_episode(tmp_path, 12, change)
    with pytest.raises(UserError, match=rf"row 13 \(task 18, episode 2, seed 18164\): task_variation: {recorded} is not "
                                        r"the placement \[0\.0861, 0\.9000, 0\.0000\] that episode 2 of drawer-close-v3 "
                                        r"starts from \(task variation 2, drawn from seed 17155\)"):
        read_cell(records / BASELINE_CELL)


# --- 2. Sequential contrasts pair only cells of one model, benchmark, suite, tasks and episode seeds ----------

SPATIAL_PI05 = "libero/libero_spatial/pi05"


def test_a_baseline_given_by_reference_contrasts_only_the_cells_of_its_model_and_suite(tmp_path, capsys):
    """On the authors' records in place: 22 other pi0.5 Spatial cells; the 42 cells of other models and suites
    are skipped, each named with the reason, instead of being decided against pi0.5 Spatial."""
    import csv

    from vlaquantbench.cli import main
    from vlaquantbench.records import find_cells

    from paths import RECORDS

    out = tmp_path / "sequential.csv"
    assert main(["sequential", str(RECORDS), "--baseline", f"{SPATIAL_PI05}/rtn-BASELINE-e2e", "--csv", str(out)]) == 0
    rows = list(csv.DictReader(out.open()))
    others = [ref for ref in find_cells(RECORDS) if not ref.startswith(f"{SPATIAL_PI05}/")]
    assert len(rows) == 22 and all(row["cell"].startswith(f"{SPATIAL_PI05}/") for row in rows)
    skipped = [line for line in capsys.readouterr().err.splitlines() if line.startswith("skipped ")]
    assert len(others) == 42
    assert skipped == [f"skipped {ref}: the baseline {SPATIAL_PI05}/rtn-BASELINE-e2e is of another model or suite"
                       for ref in others]


def test_by_default_each_model_and_suite_is_contrasted_with_its_own_baseline(tmp_path, capsys):
    import csv

    from vlaquantbench.cli import main

    from paths import RECORDS

    out = tmp_path / "sequential.csv"
    assert main(["sequential", str(RECORDS), "--csv", str(out)]) == 0
    for row in csv.DictReader(out.open()):
        assert row["baseline"] == row["cell"].rsplit("/", 1)[0] + "/rtn-BASELINE-e2e"
    err = capsys.readouterr().err
    assert (f"skipped libero/libero_object/pi05/rtn-W4A4-ah: its model and suite have no cell rtn-BASELINE-e2e in "
            f"{RECORDS}") in err


def test_a_cell_of_other_episode_seeds_is_skipped_naming_the_seeds(tmp_path, capsys):
    """A cell folder of rtn-W4A4-ah's outcomes recorded under run seed 1 (every episode seed offset by the
    protocol's run-seed stride)."""
    from vlaquantbench.cli import main
    from vlaquantbench.envs.episodes import RUN_SEED_STRIDE
    from vlaquantbench.records import read_cell, write_cell

    from paths import RECORDS

    records = tmp_path / "records"
    (records / SPATIAL_PI05).mkdir(parents=True)
    (records / SPATIAL_PI05 / "rtn-BASELINE-e2e.jsonl").symlink_to(RECORDS / SPATIAL_PI05 / "rtn-BASELINE-e2e.jsonl")
    source = read_cell(RECORDS / SPATIAL_PI05 / "rtn-W4A4-ah.jsonl")
    write_cell(records / SPATIAL_PI05 / "seed1-rtn-W4A4-ah", {**source.header, "seed": 1},
               source.episodes.assign(seed=source.episodes["seed"] + RUN_SEED_STRIDE))
    assert main(["sequential", str(records), "--csv", str(tmp_path / "out.csv")]) == 2
    err = capsys.readouterr().err
    assert (f"skipped {SPATIAL_PI05}/seed1-rtn-W4A4-ah: not comparable with {SPATIAL_PI05}/rtn-BASELINE-e2e: its "
            f"episode seeds are not the baseline's (task 0 episode 0: seed {RUN_SEED_STRIDE}, the baseline's 0)") in err
    assert f"{records} holds no cell to contrast with {SPATIAL_PI05}/rtn-BASELINE-e2e (1 skipped, above)" in err
    assert not (tmp_path / "out.csv").exists()


def test_a_live_sequential_cell_of_other_episode_seeds_is_refused_while_the_dag_is_built():
    from demo_study import demo_study

    study = demo_study("pi05", sequential={"against": "rtn-BASELINE-e2e"})
    assert cell_config(f"{SPATIAL_PI05}/rtn-W4A4-e2e", study)["sequential"]["against"]["ref"] == f"{SPATIAL_PI05}/rtn-BASELINE-e2e"
    with pytest.raises(UserError, match=rf"cell '{SPATIAL_PI05}/seed1-rtn-W4A4-e2e': study\.sequential\.against: "
                                        r"rtn-BASELINE-e2e runs its episodes with run seed 0, this cell with run seed 1"):
        cell_config(f"{SPATIAL_PI05}/seed1-rtn-W4A4-e2e", study)


def test_the_sequential_table_refuses_a_contrast_of_another_models_baseline(tmp_path):
    from paths import RECORDS
    from vlaquantbench.tables import load_table
    from vlaquantbench.tables.sequential import write_sequential_table

    cell, baseline = "libero/libero_spatial/pi0/rtn-W4A4-e2e", f"{SPATIAL_PI05}/rtn-BASELINE-e2e"
    definition = tmp_path / "mixed.yaml"
    definition.write_text(yaml.safe_dump({
        "caption": "pi0 against the pi0.5 baseline", "align": "lr", "header": [["Cell", "Delta"]],
        "values": [{"stat": "delta", "cell": "cell", "minus": "fp"}],
        "rows": [{"label": "pi0 W4A4", "cell": cell, "fp": baseline}]}))
    outputs = [tmp_path / name for name in ("sequential.tex", "sequential.csv", "sequential.pdf")]
    with pytest.raises(UserError, match=rf"tab:sequential: contrast {cell} - {baseline}: its model is pi0, the "
                                        r"baseline's pi05; a contrast pairs only cells of one model, benchmark and suite"):
        write_sequential_table([load_table(definition)], {ref: RECORDS / f"{ref}.jsonl" for ref in (cell, baseline)},
                               *outputs)
    assert not any(output.exists() for output in outputs)


# --- 5. The closed-loop measurement script refuses bad arguments before it loads the policy -------------------


@pytest.mark.parametrize(("arguments", "message"), [
    (["--episodes", "0"], "argument --episodes: 0 is less than the minimum of 1"),
    (["--first-variation", "500"],
     "argument --first-variation: the demonstrations' variations 500..539 (demonstrations.first_variation 500, "
     "max_attempts_per_task 40) meet the variations 500..504 (--first-variation 500, --episodes 5) at 500..504"),
    (["--max-steps", "501"], "argument --max-steps: 501 steps is beyond metaworld_mt50's limit of 500"),
])
def test_the_closed_loop_script_refuses_an_argument_before_loading_the_policy(tmp_path, arguments, message):
    out = tmp_path / "closed_loop.json"
    run = subprocess.run([sys.executable, "benchmarks/trained_policy_closed_loop.py", "--home", "checkpoints/pi05_metaworld_cpu",
                          "--out", str(out), *arguments], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert run.returncode == 2 and message in run.stderr, run.stderr[-3000:]
    assert "(config/trained_cpu.yaml)" in run.stderr or "--first-variation" not in arguments
    assert not out.exists()


# --- A checkpoint trained here: its folder verified against its training.json before anything reads it ------


def copied_cpu_home(root: Path) -> tuple[Path, dict]:
    import json
    import shutil

    home = root / "checkpoints" / "pi05_metaworld_cpu"
    shutil.copytree(ROOT / "checkpoints" / "pi05_metaworld_cpu", home)
    return home, json.loads((home / "training.json").read_text())


@pytest.mark.parametrize(("change", "message"), [
    ("edit", "policy/policy_postprocessor.json has SHA-256 {found}, but training.json records {recorded}: restore the file or retrain"),
    ("extra", "tokenizer/special_tokens_map.json is not recorded in training.json: remove it or retrain"),
    ("remove", "tokenizer/tokenizer_config.json is recorded in training.json but missing"),
    ("weights", "policy/model.safetensors is not the weights of this revision (its SHA-1 is {sha1}): restore the file or retrain"),
])
def test_a_changed_trained_checkpoint_folder_is_refused_naming_the_file(tmp_path, change, message):
    import hashlib

    from vlaquantbench.hub.checks import sha256
    from vlaquantbench.models.trained_home import verify

    home, training = copied_cpu_home(tmp_path)
    if change == "edit":
        edited = home / "policy" / "policy_postprocessor.json"
        edited.write_text(edited.read_text() + " ")
        message = message.format(found=sha256(edited), recorded=training["files"]["policy/policy_postprocessor.json"])
    elif change == "extra":
        (home / "tokenizer" / "special_tokens_map.json").write_text("{}")
    elif change == "remove":
        (home / "tokenizer" / "tokenizer_config.json").unlink()
    else:  # one byte of the weights file's payload: a file that still parses
        weights = home / "policy" / "model.safetensors"
        data = bytearray(weights.read_bytes())
        data[-1] ^= 0x80
        weights.write_bytes(bytes(data))
        message = message.format(sha1=hashlib.sha1(data).hexdigest())
    with pytest.raises(UserError) as refused:
        verify(home, "study.models.pi05.trained")
    assert str(refused.value) == (f"study.models.pi05.trained: {training['checkpoint']}@{training['revision']} ({home}): "
                                  f"{home}/{message}")


def test_a_changed_trained_checkpoint_folder_is_refused_while_the_dag_is_built(tmp_path):
    checkout = checkout_with_records(tmp_path)
    (checkout / "checkpoints").unlink()
    home, training = copied_cpu_home(checkout)
    (home / "tokenizer" / "tokenizer_config.json").unlink()
    status, output = dry_run(checkout, "tables/methods_2026.tex", {}, "records_dir=", "manifest=")
    assert status != 0
    assert (f"study.models.pi05.trained: {training['checkpoint']}@{training['revision']} (checkpoints/pi05_metaworld_cpu): "
            "checkpoints/pi05_metaworld_cpu/tokenizer/tokenizer_config.json is recorded in training.json but missing"
            ) in output, output[-3000:]
