"""X-VLA and OpenVLA-OFT in closed loop: their demo policies (real architectures, reduced widths, random
weights) in real LIBERO. Per model: a cell killed with kill -9 resumes to exactly the uninterrupted
records; the paper's model-specific study cells (OFT's fc2 protection, X-VLA's action-head qkv and MLP
groups) run and count the paper's layers; every header records the model's released client conventions
and the demo's overrides of them. (That an episode's actions do not depend on its batch is
test_runner_batch.py's, for every model.)"""

import json
import os
import signal
import subprocess
import sys
import time

import pandas as pd
import pytest
from demo_study import demo_study

from test_runner_resume import journal_lines, outcomes
from vlaquantbench.cells import cell_config
from vlaquantbench.records import read_cell

pytestmark = pytest.mark.slow

# X-VLA cells run in its software environment (MuJoCo 3.1.6, its client's pin)
STUDY = demo_study("openvla_oft", "xvla", max_steps=8)
RUN_CELL = ("import json, sys; from vlaquantbench.runner.cell import run_cell; "
            "run_cell(json.loads(sys.argv[1]), sys.argv[2], num_envs=int(sys.argv[3]), progress=False)")


def run_cell(cfg, folder, num_envs=1):
    """A cell in its own interpreter: X-VLA's activates its MuJoCo 3.1.6 environment before MuJoCo loads."""
    subprocess.run([sys.executable, "-c", RUN_CELL, json.dumps(cfg), str(folder), str(num_envs)], check=True,
                   timeout=1500)
    return folder


@pytest.mark.parametrize("ref", ["libero/libero_spatial/openvla_oft/ablate-W4A8-ah-only_fc2",
                                 "libero/libero_spatial/xvla/ablate-W4A4-ah-only_qkv"])
def test_kill_9_mid_cell_then_rerun_gives_exactly_the_uninterrupted_episodes(tmp_path, ref):
    cfg = cell_config(ref, {**STUDY, "episodes_per_task": 2})
    # The uninterrupted run (two envs) runs beside the interrupted one and its rerun (one env each): a cell keeps
    # about one core busy, its simulator workers and the policy taking turns.
    uninterrupted = tmp_path / "uninterrupted"
    reference = subprocess.Popen([sys.executable, "-c", RUN_CELL, json.dumps(cfg), str(uninterrupted), "2"],
                                 start_new_session=True)
    try:
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
        assert reference.wait(timeout=1500) == 0
    finally:
        if reference.poll() is None:  # a failure above: the uninterrupted run and its workers go too
            os.killpg(reference.pid, signal.SIGKILL)
            reference.wait()
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


@pytest.fixture(scope="module")
def study_cells(tmp_path_factory):
    """The study cells above, each in its own interpreter, started together when the first test needs one (a cell
    keeps about one core busy): a function from a cell's reference to its folder, once its run has ended."""
    root = tmp_path_factory.mktemp("study_cells")
    runs = {}
    for n, ref in enumerate(sorted(STUDIES)):
        folder = root / f"cell{n}"
        runs[ref] = folder, subprocess.Popen([sys.executable, "-c", RUN_CELL, json.dumps(cell_config(ref, STUDY)),
                                              str(folder), "1"], start_new_session=True)

    def finished(ref):
        folder, process = runs[ref]
        assert process.wait(timeout=1500) == 0, ref
        return folder

    yield finished
    for _, process in runs.values():
        if process.poll() is None:  # a test failed before waiting for it: the cell and its workers go
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()


@pytest.mark.parametrize("ref", sorted(STUDIES))
def test_model_specific_study_cell_runs_and_counts_the_papers_layers(study_cells, ref):
    layers, hooks, chunk = STUDIES[ref]
    header = read_cell(study_cells(ref)).header
    assert {c: v["layers"] for c, v in header["quant_report"].items()} == layers
    assert header["hooks"]["selected"] == header["hooks"]["fired"] == hooks
    assert header["chunk"] == {"predicted": chunk, "executed": chunk} and header["client"]["executed_chunk"] == chunk
    assert header["config"]["runner"]["control_mode"] == ("absolute" if "xvla" in ref else "delta")
    # The demo's episode count and step limit differ from the released client's: recorded, not silent.
    assert set(header["overrides"]) == {"episodes_per_task", "max_steps"}
    assert header["versions"]["mujoco"] == header["client"]["mujoco"]  # X-VLA 3.1.6, OFT 3.3.2
    # Random demo weights ran, not the release the study entry names for the architecture (issue 30).
    model = ref.split("/")[2]
    assert (header["checkpoint"], header["revision"]) == (f"random weights (demo variant of {model}, seed 0)", None)
    assert header["config"]["checkpoint"] == STUDY["models"][model]["checkpoint"]
