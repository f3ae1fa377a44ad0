"""`VQB_LIBERO_ASSETS`: a LIBERO assets folder named by the environment replaces the asset packages."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

from vlaquantbench.envs.libero import assets_dir, offline
from vlaquantbench.errors import UserError

# Builds LIBERO-Spatial task 0 in a fresh interpreter (the variable is read before LIBERO is imported)
# and prints every `file=` path of the model MuJoCo compiles, then LIBERO's own assets path.
_BUILD_TASK = """
import re, sys
from vlaquantbench.envs.libero import LiberoSuite, load_libero
suite = LiberoSuite("libero_spatial")
from libero.libero.envs import OffScreenRenderEnv
env = OffScreenRenderEnv(bddl_file_name=str(suite.task(0).bddl_file), camera_heights=32, camera_widths=32)
env.reset()
for path in re.findall(r'file="([^"]+)"', env.env.sim.model.get_xml()):
    print("FILE", path)
print("ASSETS", load_libero().get_assets_path())
env.close()
"""


def test_assets_folder_from_the_environment_is_used(tmp_path):
    # A linked copy: every top-level entry of the installed assets, under a new root.
    copy = tmp_path / "assets"
    copy.mkdir()
    for entry in assets_dir().iterdir():
        (copy / entry.name).symlink_to(entry)
    env = {**os.environ, "VQB_LIBERO_ASSETS": str(copy), "VQB_CACHE": str(tmp_path / "cache")}
    out = subprocess.run(
        [sys.executable, "-c", _BUILD_TASK], env=env, capture_output=True, text=True, timeout=300, check=True
    ).stdout.splitlines()
    assert f"ASSETS {copy}" in out
    files = [line.removeprefix("FILE ") for line in out if line.startswith("FILE ")]
    libero_files = [path for path in files if "robosuite" not in path]
    assert libero_files, "the task's model references no LIBERO asset files"
    for path in libero_files:
        assert Path(path).is_relative_to(copy), path
        assert Path(path).is_file(), path


def test_missing_assets_folder_is_named(tmp_path, monkeypatch):
    missing = tmp_path / "no-such-assets"
    monkeypatch.setenv(offline.ASSETS_ENV, str(missing))
    offline.assets_dir.cache_clear()
    try:
        with pytest.raises(UserError, match=f"VQB_LIBERO_ASSETS={missing} is not an existing folder"):
            offline.assets_dir()
    finally:
        offline.assets_dir.cache_clear()
