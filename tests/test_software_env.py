"""envs/: the main lock matches the venv the setup builds, and X-VLA cells run LIBERO on MuJoCo 3.1.6."""

import json
import shutil
import subprocess
import sys

from vlaquantbench import software_env
from vlaquantbench.envs.libero import PINNED_MUJOCO
from vlaquantbench.models.client import environment_name
from vlaquantbench.software_env import MAIN, Environment, stale_lines


def test_main_lock_pins_exactly_the_installed_requirements():
    assert stale_lines() == [], "envs/main.lock.txt is stale: python -m vlaquantbench.software_env lock"
    assert Environment(MAIN).mujoco == PINNED_MUJOCO and environment_name("pi05") == MAIN


def test_a_stale_lock_names_each_difference(tmp_path, monkeypatch):
    lines = Environment(MAIN).lock.read_text().splitlines()
    edited = [line.replace("mujoco==3.3.2", "mujoco==3.4.0") for line in lines if not line.startswith("scipy==")]
    (tmp_path / "main.lock.txt").write_text("\n".join(edited) + "\n")
    monkeypatch.setattr(software_env, "ENVS_DIR", tmp_path)
    stale = stale_lines()
    assert "mujoco: locked 3.4.0, installed 3.3.2" in stale
    assert [line for line in stale if line.startswith("scipy: locked nothing, installed ")]
    assert len(stale) == 2


XVLA_CELL_PROCESS = """
import json, subprocess, sys
import numpy as np
from vlaquantbench.models.client import environment_name
from vlaquantbench.software_env import Environment, activate
env = Environment(environment_name("xvla"))
activate(env)  # what CellRun does first for an X-VLA cell
from vlaquantbench.envs.libero import LiberoSuite, LiberoVectorEnv, simulator_versions
from vlaquantbench.envs.workers import worker_environment
suite = LiberoSuite("libero_spatial")
with LiberoVectorEnv(suite, 1, camera_size=32, settle_steps=1) as venv:
    venv.reset([suite.episode_spec(0, 0, 0)])
    observations, _ = venv.step(np.zeros((1, 7)))
worker = subprocess.run([sys.executable, "-c", "import mujoco; print(mujoco.__version__)"],
                        env=worker_environment(), capture_output=True, text=True, check=True).stdout.strip()
print(json.dumps({"versions": simulator_versions(), "worker_mujoco": worker, "environment": env.describe(),
                  "state": observations[0]["state"].tolist()}))
"""


def test_xvla_cells_run_libero_on_the_mujoco_of_their_overlay(tmp_path):
    run = subprocess.run([sys.executable, "-c", XVLA_CELL_PROCESS], cwd=tmp_path, capture_output=True, text=True,
                         timeout=600)  # fmt: skip
    assert run.returncode == 0, run.stderr[-3000:]
    result = json.loads(run.stdout.splitlines()[-1])
    assert result["versions"]["mujoco"] == result["versions"]["mujoco_pinned"] == "3.1.6"
    assert result["versions"]["mujoco_pin_overridden"] is False
    assert result["worker_mujoco"] == "3.1.6"  # the LIBERO worker processes simulate on it too
    assert result["environment"]["name"] == "xvla" and result["environment"]["mujoco"] == "3.1.6"
    assert len(result["state"]) == 8
