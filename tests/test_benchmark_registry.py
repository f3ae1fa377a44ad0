"""Benchmarks declare themselves (issue 50): each folder `envs/<benchmark>/` registers its declaration from its own
`benchmark.py`, found without importing a simulator; the protocol module and the registry name no benchmark."""

from __future__ import annotations

import dataclasses
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
