"""Floating-point format cells in closed loop: real LIBERO episodes of the demo pi0.5 under MXFP4 and
NVFP4 on the action head, every input hook counted, the exact format in the header."""

import json

import pandas as pd
import pytest
from demo_study import demo_study

from vlaquantbench.cells import cell_config
from vlaquantbench.runner.cell import run_cell

pytestmark = pytest.mark.slow

STUDY = demo_study()


def test_mxfp4_and_nvfp4_action_head_cells_run_with_every_hook_fired(tmp_path):
    actions = {}
    for preset, words in [("MXFP4", "OCP MX v1.0, E2M1 elements in blocks of 32"),
                          ("NVFP4", "E2M1 elements in blocks of 16 along the input dimension, E4M3 block scale x FP32 scale")]:
        cfg = cell_config(f"libero/libero_spatial/pi05/rtn-{preset}-ah", STUDY)
        folder = run_cell(cfg, tmp_path / preset, num_envs=1, progress=False).parent
        header = json.loads((folder / "header.json").read_text())
        assert header["preset"] == preset
        assert f"weights {preset}: {words}" in header["quant_format"]
        assert f"activations {preset}: {words}" in header["quant_format"]
        assert header["hooks"] == {"selected": 167, "fired": 167, "unfired": []}
        assert header["quant_report"]["ah"]["layers"] == 167
        episodes = pd.read_parquet(folder / "episodes.parquet")
        assert len(episodes) == 1 and episodes["steps"].iloc[0] <= 10
        journal = [json.loads(line) for line in (folder / "journal.jsonl").read_text().splitlines()]
        actions[preset] = [r["actions_sha256"] for r in journal if r["kind"] == "episode"]
    assert actions["MXFP4"] != actions["NVFP4"]  # two formats, two trajectories
