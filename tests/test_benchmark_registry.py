"""Benchmarks declare themselves (issue 50): each folder `envs/<benchmark>/` registers its declaration from its own
`benchmark.py`, found without importing a simulator; the protocol module and the registry name no benchmark."""

from __future__ import annotations

import dataclasses
import json
import re
import subprocess
import sys

import pytest

from paths import ROOT
from vlaquantbench.envs import BENCHMARK_SUITES, make_suite
from vlaquantbench.envs.registry import get_benchmark, register_benchmark
from vlaquantbench.errors import UserError

ENVS = ROOT / "src" / "vlaquantbench" / "envs"


def test_every_benchmark_folder_is_registered_from_its_own_declaration():
    folders = sorted(p.parent.name for p in ENVS.glob("*/benchmark.py"))
    assert folders == ["libero", "metaworld"] and list(BENCHMARK_SUITES) == folders
    for name in folders:
        benchmark = get_benchmark(name)
        suite = next(iter(benchmark.suites))
        assert benchmark.resolve("suite_class").__module__.startswith(f"vlaquantbench.envs.{name}.")
        assert make_suite(name, suite).name == suite


def test_the_suites_are_known_without_a_simulator_import():
    code = ("import sys; from vlaquantbench.envs import BENCHMARK_SUITES; sizes = dict(BENCHMARK_SUITES); "
            "print(sorted(sizes), [m for m in ('libero.libero', 'robosuite', 'metaworld', 'mujoco') if m in sys.modules])")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env={"PYTHONPATH": str(ROOT / "src")}).stdout
    assert out.strip() == "['libero', 'metaworld'] []"


def test_a_second_declaration_under_a_registered_name_is_refused():
    libero = get_benchmark("libero")
    assert register_benchmark(libero) is libero  # the same declaration again (a module imported twice) is fine
    with pytest.raises(UserError, match="benchmark 'libero' is declared twice"):
        register_benchmark(dataclasses.replace(libero, suite_class="elsewhere:Suite"))


@pytest.mark.parametrize("module", ["__init__.py", "registry.py", "memory.py"])
def test_the_protocol_names_no_benchmark(module):
    source = (ENVS / module).read_text()
    assert not re.findall(r"(?i)libero|meta-?world", source), module


def test_a_declaration_names_its_cameras_by_role():
    libero = get_benchmark("libero")
    with pytest.raises(UserError, match=r"benchmark 'libero': cameras \['side'\]: the roles are main, wrist"):
        register_benchmark(dataclasses.replace(libero, cameras={"side": "agentview"}))
    with pytest.raises(UserError, match="a main camera is required"):
        register_benchmark(dataclasses.replace(libero, cameras={"wrist": "wrist"}))
    # what replay records of each benchmark's observations: each declared camera's image, then the state
    assert get_benchmark("metaworld").observed == ("image", "state")


def test_the_declared_action_and_state_sizes_are_the_simulators_and_lerobots():
    """Each benchmark declares the sizes of its action and state without importing its simulator: those its vector
    env steps with, and lerobot's env features (Meta-World's action and `agent_pos`; LIBERO's action, and the state
    its worker assembles from lerobot's end-effector position, axis-angle and gripper joints)."""
    from lerobot.envs.configs import LiberoEnv, MetaworldEnv

    from vlaquantbench.envs.libero import LiberoVectorEnv
    from vlaquantbench.envs.metaworld import MetaWorldVectorEnv

    metaworld, libero = MetaworldEnv().features, LiberoEnv().features
    assert (get_benchmark("metaworld").action_dim, get_benchmark("metaworld").state_dim) == \
        (MetaWorldVectorEnv.action_dim, *metaworld["agent_pos"].shape) == (*metaworld["action"].shape, 4)
    assert (get_benchmark("libero").action_dim, get_benchmark("libero").state_dim) == \
        (LiberoVectorEnv.action_dim, 3 + 3 + libero["robot_state/gripper/qpos"].shape[0]) == (*libero["action"].shape, 8)


@pytest.mark.parametrize("dim", [0, -1, 2.0, True])
def test_an_action_or_state_size_that_is_no_positive_integer_is_refused(dim):
    libero = get_benchmark("libero")
    for what in ("action_dim", "state_dim"):
        with pytest.raises(UserError, match=rf"benchmark 'libero': {what} {dim!r} is not a positive integer"):
            register_benchmark(dataclasses.replace(libero, **{what: dim}))


def test_a_scripted_expert_naming_other_than_the_declared_components_is_refused():
    metaworld = get_benchmark("metaworld")
    with pytest.raises(UserError, match=r"benchmark 'metaworld': its scripted expert's action_names \['dx', 'dy', 'dz'\] "
                                        r"name 3 components, but it declares action_dim 4"):
        register_benchmark(dataclasses.replace(metaworld, scripted_expert=dataclasses.replace(
            metaworld.scripted_expert, action_names=("dx", "dy", "dz"))))
    with pytest.raises(UserError, match=r"its scripted expert's state_names .* name 4 components, but it declares state_dim 5"):
        register_benchmark(dataclasses.replace(metaworld, state_dim=5))


def test_the_declared_scripted_expert_is_the_simulators_and_lerobots():
    """Meta-World's declaration says what its demonstrations hold without importing them: as many names as the
    state and action it declares, lerobot's frame rate for it, an expert model of the registry; LIBERO declares none."""
    from lerobot.envs.configs import MetaworldEnv

    from vlaquantbench.models.registry import MODELS

    metaworld = get_benchmark("metaworld")
    expert = metaworld.scripted_expert
    assert (len(expert.state_names), len(expert.action_names), expert.fps) == \
        (metaworld.state_dim, metaworld.action_dim, MetaworldEnv.fps)
    assert expert.model in MODELS and expert.suite in get_benchmark("metaworld").suites
    assert get_benchmark("libero").scripted_expert is None


def test_a_scripted_expert_on_a_suite_the_benchmark_lacks_is_refused():
    metaworld = get_benchmark("metaworld")
    elsewhere = dataclasses.replace(metaworld.scripted_expert, suite="libero_spatial")
    with pytest.raises(UserError, match=r"benchmark 'metaworld': its scripted expert's suite 'libero_spatial' is not "
                                        r"one of its suites \(metaworld_easy, "):
        register_benchmark(dataclasses.replace(metaworld, scripted_expert=elsewhere))


def test_an_observation_without_a_named_benchmark_has_the_cameras_of_the_declaration_its_keys_fit():
    from vlaquantbench.envs.registry import cameras_of

    assert cameras_of({"agentview", "wrist", "state", "instruction"}) == get_benchmark("libero").cameras
    assert cameras_of({"image", "state", "instruction"}) == get_benchmark("metaworld").cameras
    assert cameras_of({"wrist", "state", "instruction"}) == {}  # no declaration's every camera


def test_each_benchmark_declares_its_env_settings_as_the_vector_envs_keyword_parameters():
    import inspect

    from vlaquantbench.envs import benchmark_settings, env_settings

    for name in BENCHMARK_SUITES:
        benchmark = get_benchmark(name)
        parameters = inspect.signature(benchmark.resolve("env_class")).parameters
        for setting in dataclasses.fields(benchmark.settings):
            # each setting is the env's keyword-only parameter of the same name, with the env's default
            assert parameters[setting.name].kind is inspect.Parameter.KEYWORD_ONLY, (name, setting.name)
            assert parameters[setting.name].default == setting.default, (name, setting.name)
    assert get_benchmark("libero").setting_names == ("camera_size", "settle_steps", "control_mode", "mujoco")
    assert get_benchmark("metaworld").setting_names == ("camera_size", "mujoco")
    # a cell's env gets exactly its benchmark's declared settings: those given, then the client's conventions for
    # the ones it declares, the declared defaults elsewhere
    client = {"control_mode": "absolute", "mujoco": "3.3.2", "executed_chunk": 5}
    metaworld = benchmark_settings("metaworld", {"camera_size": 64}, {"camera_size": "study.runner.camera_size"}, client)
    assert env_settings(metaworld) == {"camera_size": 64, "mujoco": "3.3.2"}
    assert env_settings(metaworld, reads_images=False) == {"camera_size": None, "mujoco": "3.3.2"}
    assert env_settings(benchmark_settings("metaworld", {}, {})) == {"camera_size": 480, "mujoco": None}
    libero = benchmark_settings("libero", {"settle_steps": 3}, {"settle_steps": "study.runner.settle_steps"}, client)
    assert env_settings(libero) == {"camera_size": 256, "settle_steps": 3, "control_mode": "absolute", "mujoco": "3.3.2"}


def test_a_setting_of_the_wrong_type_or_out_of_its_declared_range_is_refused_by_field():
    from vlaquantbench.envs import benchmark_settings

    for value, problem in (("big", r"'big' is not of type 'integer'"), (8, r"8 is less than the minimum of 16"),
                           (True, r"True is not of type 'integer'")):
        with pytest.raises(UserError, match=rf"^study\.runner\.camera_size: {problem} \(libero's env setting camera_size"):
            benchmark_settings("libero", {"camera_size": value}, {"camera_size": "study.runner.camera_size"})
    with pytest.raises(UserError, match=r"^f: 'relative' is not one of \['delta', 'absolute'\] \(libero's env setting "
                                        r"control_mode"):
        benchmark_settings("libero", {"control_mode": "relative"}, {"control_mode": "f"})


def test_a_declaration_without_a_settings_dataclass_is_refused():
    libero = get_benchmark("libero")
    with pytest.raises(UserError, match=r"benchmark 'libero': settings \{'settle_steps': 10\} is not a dataclass"):
        register_benchmark(dataclasses.replace(libero, settings={"settle_steps": 10}))


def test_a_declaration_whose_settings_a_config_could_not_give_is_refused():
    libero = get_benchmark("libero")
    for body, problem in (("camera_size: int\n", r"env setting 'camera_size' has no default"),
                          ("camera_size: list = ()\n", r"env setting 'camera_size': type <class 'list'> is not one a config "
                                                        r"can give"),
                          ("camera_size: int = dataclasses.field(default=8, metadata={'schema': {'minimum': 16}})\n",
                           r"env setting 'camera_size': its default 8 does not satisfy its rules")):
        namespace = {"dataclasses": dataclasses}
        exec(f"@dataclasses.dataclass(frozen=True)\nclass Settings:\n    {body}", namespace)
        with pytest.raises(UserError, match=rf"^benchmark 'libero': {problem}"):
            register_benchmark(dataclasses.replace(libero, settings=namespace["Settings"]))


def test_a_setting_given_for_a_benchmark_that_does_not_declare_it_is_refused_by_field():
    from vlaquantbench.envs import check_settings

    check_settings("libero", {"settle_steps": "study.runner.settle_steps"})
    check_settings("metaworld", {"camera_size": "study.runner.camera_size"})
    with pytest.raises(UserError, match=r"^study\.runner\.settle_steps: 'settle_steps' is not an env setting of "
                                        r"metaworld \(it takes camera_size, mujoco; settle_steps is libero's\); "
                                        r"study\.runner\.control_mode: 'control_mode' is not"):
        check_settings("metaworld", {"settle_steps": "study.runner.settle_steps",
                                     "control_mode": "study.runner.control_mode"})
    # a key that is no runner option and no benchmark's setting (a misspelt one) is refused the same way
    with pytest.raises(UserError, match=r"^study\.runner\.camera_sise: 'camera_sise' is not an env setting of libero "
                                        r"\(it takes camera_size, settle_steps, control_mode, mujoco; no registered "
                                        r"benchmark takes camera_sise\); remove it$"):
        check_settings("libero", {"camera_sise": "study.runner.camera_sise"})


def test_a_benchmark_outside_envs_is_registered_from_the_module_vqb_benchmarks_names(tmp_path):
    """The hook a benchmark package outside `src/` (tests/contract_benchmark) registers through."""
    (tmp_path / "outside_benchmark.py").write_text(
        "import dataclasses\n"
        "from vlaquantbench.envs.registry import Benchmark, Horizon, SuiteSize, register_benchmark\n"
        "@dataclasses.dataclass(frozen=True)\n"
        "class Settings:\n    camera_size: int = 32\n    lighting: float = 1.0\n"
        "register_benchmark(Benchmark('outside', {'outside_one': SuiteSize(2, 3, 0.1, Horizon(9, 'here'), 9)},\n"
        "    'x:Suite', 'x:Env', 'x:versions', {'main': 'image'}, Settings, 4, 4))\n")
    code = "from vlaquantbench.envs import BENCHMARK_SUITES as b; print(sorted(b), b['outside']['outside_one'].tasks)"
    env = {"PYTHONPATH": f"{ROOT / 'src'}:{tmp_path}", "VQB_BENCHMARKS": "outside_benchmark"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=env).stdout
    assert out.strip() == "['libero', 'metaworld', 'outside'] 2"
    # its own setting `lighting`, which no runner option names, is read back from a cell's runner with its type checked
    read = ("from vlaquantbench.cells import cell_runner\n"
            "print(cell_runner('cell x', 'outside', {'device': 'cpu', 'lighting': 0.5})[1])\n"
            "try: cell_runner('cell x', 'outside', {'lighting': 'dim'})\nexcept Exception as err: print(err)")
    out = subprocess.run([sys.executable, "-c", read], capture_output=True, text=True, check=True, env=env).stdout
    assert out.splitlines() == ["Settings(camera_size=32, lighting=0.5)",
                                "cell x: runner.lighting: 'dim' is not of type 'number' (outside's env setting lighting: "
                                "{'type': ['number']})"]
    # a setting named like a runner option would share study.runner with it: refused when a cell is built
    (tmp_path / "clashing_benchmark.py").write_text(
        (tmp_path / "outside_benchmark.py").read_text().replace("lighting: float = 1.0", "device: str = 'gpu'")
        .replace("'outside'", "'clashing'").replace("outside_one", "clashing_one"))
    clash = "from vlaquantbench.cells import cell_runner\ntry: cell_runner('cell x', 'clashing', {})\nexcept Exception as err: print(err)"
    out = subprocess.run([sys.executable, "-c", clash], capture_output=True, text=True, check=True,
                         env={**env, "VQB_BENCHMARKS": "clashing_benchmark"}).stdout
    assert out.strip() == ("benchmark 'clashing' declares env setting(s) device, named like runner options "
                           "(config.study.RunnerConfig), which share study.runner with them: rename them")
    env["VQB_BENCHMARKS"] = "no_such_benchmark_module"
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env)
    assert run.returncode != 0 and "VQB_BENCHMARKS: cannot import benchmark declaration module 'no_such_benchmark_module'" in run.stderr


def test_threads_reading_the_registry_first_all_see_every_benchmark(tmp_path):
    """The registry is found on first read; a thread reading while another is finding it waits for the end (a
    declaration module that takes its time to import: here the second thread starts meanwhile)."""
    (tmp_path / "slow_benchmark.py").write_text(
        "import dataclasses, time\n"
        "from vlaquantbench.envs.registry import Benchmark, Horizon, SuiteSize, register_benchmark\n"
        "time.sleep(1.0)\n"
        "@dataclasses.dataclass(frozen=True)\n"
        "class Settings:\n    camera_size: int = 32\n"
        "register_benchmark(Benchmark('slow', {'slow_one': SuiteSize(2, 3, 0.1, Horizon(9, 'here'), 9)},\n"
        "    'x:Suite', 'x:Env', 'x:versions', {'main': 'image'}, Settings, 4, 4))\n")
    code = ("import threading, time\n"
            "from vlaquantbench.envs import BENCHMARK_SUITES\n"
            "seen = []\n"
            "def read(): seen.append(sorted(BENCHMARK_SUITES))\n"
            "first = threading.Thread(target=read); first.start(); time.sleep(0.3)\n"
            "second = threading.Thread(target=read); second.start(); first.join(); second.join()\n"
            "print(seen)")
    env = {"PYTHONPATH": f"{ROOT / 'src'}:{tmp_path}", "VQB_BENCHMARKS": "slow_benchmark"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=env).stdout
    assert out.strip() == str([["libero", "metaworld", "slow"]] * 2)


def test_the_committed_seam_equality_run_found_every_episode_of_both_benchmarks_equal():
    """benchmarks/seam_equality.py's record (minutes of Snakemake runs, so read here, not rerun): both benchmarks'
    demos ran before and after the seam's refactor, on the same cells, with no episode differing."""
    report = json.loads((ROOT / "benchmarks" / "results" / "seam_equality.json").read_text())
    assert report["revisions"]["before"]["commit"] != report["revisions"]["after"]["commit"]
    assert set(report["benchmarks"]) == {"libero", "metaworld"}
    for benchmark, run in report["benchmarks"].items():
        assert run["cells"] and all(hashes["before"] and hashes["after"] for hashes in run["cells"].values()), benchmark
        assert run["episodes"]["before"] == run["episodes"]["after"] == run["equal"] > 0, benchmark
        assert run["differences"] == [], benchmark
    assert set(report["fields"]) == {"success", "steps", "actions_sha256"}
