"""`vqb methods` lists what cell names accept: every registered method, with presets, statistics,
transforms and options that the cell grammar and the registry agree with."""

import json
import subprocess
import sys

import pytest

from vlaquantbench.cells import cell_config
from vlaquantbench.errors import UserError
from vlaquantbench.quant.methods import registered_methods

STUDY = {"models": {"pi05": {"variant": "demo"}}, "tasks": 1, "episodes_per_task": 1}
# an example preset of each listed form, and one it refuses
EXAMPLES = {"any preset": ("W4A8", None), "W<b>[G<g>]": ("W4G64", "W4A8"), "W<b>[G<g>][A<a>]": ("W3A8", "FP8E4M3")}


def vqb(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "vlaquantbench.cli", *args], capture_output=True, text=True,
                          timeout=120)


def test_every_listed_method_is_one_a_cell_name_accepts():
    listed = vqb("methods", "--json")
    assert listed.returncode == 0, listed.stderr
    rows = {row["method"]: row for row in json.loads(listed.stdout)}
    assert sorted(rows) == registered_methods()
    assert rows["gptq"]["statistics"] == ["hessian", "rows"] and rows["gptq"]["options"]["damp"] == 0.01
    assert rows["hadamard_gptq"]["transforms"] == ["hadamard"]
    assert not rows["step_static"]["captured"] and "flow-step clock" in rows["step_static"]["uncapturable"]
    for name, row in rows.items():
        good, bad = EXAMPLES.get(row["presets"], (row["presets"], "W2A2"))
        cfg = cell_config(f"libero/libero_spatial/pi05/{name}-{good}-e2e", STUDY)
        assert cfg["method"] == name and cfg["preset"] == good
        # the statistics it lists are what its cell's calibration collects
        calibration = cfg.get("calibration") or {}
        assert bool(calibration.get("hessian")) == ("hessian" in row["statistics"]), name
        assert bool(calibration.get("step_scales")) == ("step_scales" in row["statistics"]), name
        assert (cfg.get("calibration") is not None) == bool(row["statistics"]), name
        if bad is not None:
            with pytest.raises(UserError, match=f"method '{name}'"):
                cell_config(f"libero/libero_spatial/pi05/{name}-{bad}-e2e", STUDY)


def test_the_table_names_every_method_and_why_some_are_not_captured():
    table = vqb("methods")
    assert table.returncode == 0, table.stderr
    lines = table.stdout.splitlines()
    assert lines[0].split()[:2] == ["method", "presets"]
    assert {line.split()[0] for line in lines[1:1 + len(registered_methods())]} == set(registered_methods())
    assert any(line.startswith("int8: not captured: bitsandbytes") for line in lines)
