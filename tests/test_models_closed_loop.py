"""X-VLA and OpenVLA-OFT in closed loop: their demo policies (real architectures, reduced widths, random
weights) in real LIBERO. Per model: an episode's actions do not depend on its batch; a cell killed with
kill -9 resumes to exactly the uninterrupted records; the paper's model-specific study cells (OFT's fc2
protection, X-VLA's action-head qkv and MLP groups) run and count the paper's layers; every header records
the model's released client conventions and the demo's overrides of them."""

import json
import os
import signal
import subprocess
import sys
import time
from collections import defaultdict

import numpy as np
import pandas as pd
import pytest

from test_runner_resume import journal_lines, outcomes
from vlaquantbench.cells import cell_config
from vlaquantbench.envs.libero import LiberoSuite, LiberoVectorEnv
from vlaquantbench.models.adapter import AdapterConfig, make_adapter
from vlaquantbench.quant import QuantConfig, quantize_
from vlaquantbench.records import read_cell
from vlaquantbench.runner.loop import run_episodes

pytestmark = pytest.mark.slow

STUDY = {
    "models": {
        "openvla_oft": {"variant": "demo", "checkpoint": "moojink/openvla-7b-oft-finetuned-libero-spatial"},
        # X-VLA cells run in its software environment (MuJoCo 3.1.6, its client's pin)
        "xvla": {"variant": "demo", "checkpoint": "2toINF/X-VLA-Libero"},
    },
    "tasks": [0],
    "episodes_per_task": 1,
    "runner": {"max_steps": 8, "camera_size": 64, "flow_steps": 2},
}
RUN_CELL = ("import json, sys; from vlaquantbench.runner.cell import run_cell; "
            "run_cell(json.loads(sys.argv[1]), sys.argv[2], num_envs=int(sys.argv[3]), progress=False)")


def run_cell(cfg, folder, num_envs=1):
    """A cell in its own interpreter: X-VLA's activates its MuJoCo 3.1.6 environment before MuJoCo loads."""
    subprocess.run([sys.executable, "-c", RUN_CELL, json.dumps(cfg), str(folder), str(num_envs)], check=True,
                   timeout=1500)
    return folder


@pytest.mark.parametrize("model", ["openvla_oft", "xvla"])
def test_batch_of_two_equals_batch_of_one(model):
    suite = LiberoSuite("libero_spatial")
    specs = [suite.episode_spec(0, 0), suite.episode_spec(1, 0)]
    adapter = make_adapter(AdapterConfig(model=model, variant="demo", flow_steps=2, executed_chunk=4))
    adapter.load()
    config = QuantConfig.from_preset("W4A4", scope="ah")
    report = quantize_(adapter.model, config, config.select(adapter.model, adapter.components))
    chunks = defaultdict(list)  # episode seed -> [(state observed, chunk predicted)]
    act = adapter.act

    def recording_act(observations, generators):
        out = act(observations, generators)
        for obs, generator, chunk in zip(observations, generators, out):
            chunks[generator.initial_seed()].append((obs["state"].copy(), chunk.copy()))
        return out

    adapter.act = recording_act

    def run(num_envs):
        chunks.clear()
        records = []
        with LiberoVectorEnv(suite, num_envs, camera_size=64, control_mode=adapter.control_mode) as env:
            run_episodes(adapter, env, specs, max_steps=8, on_finished=records.extend)
        return sorted(records, key=lambda r: r["task_id"]), {seed: list(calls) for seed, calls in chunks.items()}

    batched, batched_chunks = run(2)
    single, single_chunks = run(1)
    for a, b in zip(batched, single):
        assert (a["steps"], a["actions_sha256"]) == (b["steps"], b["actions_sha256"])
    assert batched_chunks.keys() == single_chunks.keys() == {0, 1009}
    for seed in batched_chunks:
        assert len(batched_chunks[seed]) == len(single_chunks[seed]) == 2  # 8 steps, 4 executed per chunk
        for (state_a, chunk_a), (state_b, chunk_b) in zip(batched_chunks[seed], single_chunks[seed]):
            assert np.array_equal(state_a, state_b) and np.array_equal(chunk_a, chunk_b)
    assert batched[0]["actions_sha256"] != batched[1]["actions_sha256"]
    assert not report.unfired()


@pytest.mark.parametrize("ref", ["libero/libero_spatial/openvla_oft/ablate-W4A8-ah-only_fc2",
                                 "libero/libero_spatial/xvla/ablate-W4A4-ah-only_qkv"])
def test_kill_9_mid_cell_then_rerun_gives_exactly_the_uninterrupted_episodes(tmp_path, ref):
    cfg = cell_config(ref, {**STUDY, "episodes_per_task": 2})
    interrupted = tmp_path / "interrupted"
    process = subprocess.Popen([sys.executable, "-c", RUN_CELL, json.dumps(cfg), str(interrupted), "1"],
                               start_new_session=True)
    deadline = time.monotonic() + 900
    while not any(r["kind"] == "episode" for r in journal_lines(interrupted / "journal.jsonl")):
        assert process.poll() is None, "the cell ended before it could be killed"
        assert time.monotonic() < deadline, "no episode finished in time"
        time.sleep(0.2)
    os.killpg(process.pid, signal.SIGKILL)  # the runner and its LIBERO workers, mid-cell
    process.wait()
    done_before = outcomes(interrupted)
    assert len(done_before) == 1 and not (interrupted / "episodes.parquet").exists()

    run_cell(cfg, interrupted)
    uninterrupted = tmp_path / "uninterrupted"
    run_cell(cfg, uninterrupted, num_envs=2)
    resumed = outcomes(interrupted)
    assert resumed == outcomes(uninterrupted) and len(resumed) == 2
    assert {k: resumed[k] for k in done_before} == done_before
    frames = [pd.read_parquet(folder / "episodes.parquet") for folder in (interrupted, uninterrupted)]
    episodes, other = (f.drop(columns=[c for c in f.columns if "latency" in c or "wall_time" in c]) for f in frames)
    assert episodes.equals(other)
    # The study's own scope, counted as the paper does: OFT's one fc2 layer, X-VLA's 24 qkv projections.
    header = read_cell(interrupted).header
    layers = {"openvla_oft": 1, "xvla": 24}[header["model"]]
    assert {c: v["layers"] for c, v in header["quant_report"].items()} == {"ah": layers}
    assert header["hooks"]["selected"] == header["hooks"]["fired"] == layers


STUDIES = {
    # the 441 eligible layers but the head's fc2 (VE 209, MP 5, LLM 224, AH 3), W3 weight-only: no hooks
    "libero/libero_10/openvla_oft/ablate-W3-e2e-no_ah_fc2": ({"ve": 209, "mp": 5, "llm": 224, "ah": 3}, 0, 8),
    # X-VLA's two MLP projection groups of the 24 head blocks, W4A4: 48 hooks, all fired
    "libero/libero_spatial/xvla/ablate-W4A4-ah-onlymlp": ({"ah": 48}, 48, 30),
}


@pytest.mark.parametrize("ref", sorted(STUDIES))
def test_model_specific_study_cell_runs_and_counts_the_papers_layers(tmp_path, ref):
    layers, hooks, chunk = STUDIES[ref]
    header = read_cell(run_cell(cell_config(ref, STUDY), tmp_path / "cell")).header
    assert {c: v["layers"] for c, v in header["quant_report"].items()} == layers
    assert header["hooks"]["selected"] == header["hooks"]["fired"] == hooks
    assert header["chunk"] == {"predicted": chunk, "executed": chunk} and header["client"]["executed_chunk"] == chunk
    assert header["config"]["runner"]["control_mode"] == ("absolute" if "xvla" in ref else "delta")
    # The demo's episode count and step limit differ from the released client's: recorded, not silent.
    assert set(header["overrides"]) == {"episodes_per_task", "max_steps"}
    assert header["versions"]["mujoco"] == header["client"]["mujoco"]  # X-VLA 3.1.6, OFT 3.3.2
