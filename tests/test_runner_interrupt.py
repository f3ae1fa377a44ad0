"""A real `vqb rollout` stopped or doubled: Ctrl-C or SIGTERM prints one line saying how far the cell got and
that rerunning resumes it, no traceback, exit 130 / 143, the journal intact, no LIBERO worker left; a
second `vqb rollout` of a running cell is refused naming the first, which completes alone; a cell
terminated mid-way and resumed records what an uninterrupted one does."""

import json
import os
import signal
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from types import SimpleNamespace

import pandas as pd
import pytest
import yaml
from test_runner_resume import outcomes
from vlaquantbench.runner.journal import TIMING_FIELDS

pytestmark = pytest.mark.slow

REF = "libero/libero_spatial/pi05/rtn-W4A4-ah"
STUDY = {
    "models": {"pi05": {"variant": "demo", "checkpoint": "lerobot/pi05_libero_finetuned_v044"}},
    "tasks": [0],
    "episodes_per_task": 3,
    "runner": {"max_steps": 10, "camera_size": 64, "flow_steps": 2},
    "execution": {"num_envs": 1},
}


def rollout(results):
    """`vqb rollout REF` of STUDY into `results`, as its own session (process group = its pid)."""
    config = results / "study.yaml"
    config.write_text(yaml.safe_dump({"study": STUDY}))
    return [sys.executable, "-m", "vlaquantbench.cli", "rollout", REF, "--config", str(config), "--results", str(results)]


def cell_folder(results):
    # `--config` is merged over the checkout's config/config.yaml as Snakemake merges it, so the
    # cell's folder (its config hash) is found rather than recomputed from STUDY alone.
    found = sorted((results / "results").rglob("writer.lock"))
    return found[0].parent if found else None


def episodes(results):
    folder = cell_folder(results)
    path = folder / "journal.jsonl" if folder else None
    lines = path.read_text().splitlines() if path and path.exists() else []
    return sum(json.loads(line)["kind"] == "episode" for line in lines)


def wait_for(process, condition, what):
    deadline = time.monotonic() + 900
    while not condition():
        assert process.poll() is None, process.communicate()
        assert time.monotonic() < deadline, f"{what} did not happen in time"
        time.sleep(0.2)


def interrupt_after_an_episode(results, send, **popen):
    """Start the cell, deliver a signal with `send(process)` once an episode is journaled; its stderr."""
    process = subprocess.Popen(rollout(results), start_new_session=True, stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True, **popen)
    try:
        wait_for(process, lambda: episodes(results) >= 1, "an episode")
        send(process)
        _, stderr = process.communicate(timeout=120)
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()
    return process, stderr


def test_ctrl_c_prints_how_far_the_cell_got_and_that_rerunning_resumes(tmp_path):
    process, stderr = interrupt_after_an_episode(
        tmp_path,
        lambda process: os.killpg(process.pid, signal.SIGINT),  # a terminal's Ctrl-C: the whole foreground group
        # A terminal's foreground job has SIGINT at its default. Started in the background (`cmd &`
        # in a script), the suite itself would have it ignored, and the cell would inherit that.
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    assert process.returncode == 130
    assert "Traceback" not in stderr and "KeyboardInterrupt" not in stderr
    done = episodes(tmp_path)
    folder = cell_folder(tmp_path)
    assert 1 <= done < 3
    message = (f"vqb rollout: interrupted: {REF} has {done} of 3 episodes recorded in {folder}; "
               "run the same command again to resume it")
    # The progress bar may redraw its last state after the message (tqdm closes at exit).
    assert stderr.splitlines().count(message) == 1, stderr[-2000:]
    assert not (folder / "episodes.parquet").exists()


@pytest.fixture(scope="module")
def two_writers(tmp_path_factory):
    """A cell run to the end while a second `vqb rollout` of it, started once the first holds the cell,
    tries to run too: the first's records (an uninterrupted run's) and the second's result. Returned once the
    second is refused, the first still running (the SIGTERM test's runs go beside it); `finished()` waits for
    the first and gives its stderr (read as it comes)."""
    results = tmp_path_factory.mktemp("two_writers")
    first = subprocess.Popen(rollout(results), start_new_session=True, stderr=subprocess.PIPE, text=True)

    def holds():
        folder = cell_folder(results)
        try:  # the holder writes its name just after it takes the lock
            return folder is not None and json.loads((folder / "writer.lock").read_text())["pid"] == first.pid
        except ValueError:
            return False

    with ThreadPoolExecutor(1) as reader:
        try:
            wait_for(first, holds, "the first writer's lock")
            began = time.monotonic()
            second = subprocess.run(rollout(results), capture_output=True, text=True, timeout=600)
            refused_after = time.monotonic() - began
            alive_then = first.poll() is None
            first_run = reader.submit(first.communicate, timeout=900)
            yield SimpleNamespace(results=results, first=first, finished=lambda: first_run.result()[1], second=second,
                                  refused_after=refused_after, alive_then=alive_then)
        finally:
            if first.poll() is None:  # a failure: the first writer and its workers go too
                os.killpg(first.pid, signal.SIGKILL)
                first.wait()


def test_sigterm_prints_how_far_the_cell_got_stops_the_workers_and_a_rerun_resumes_exactly(tmp_path, two_writers):
    # `kill PID`, the runner alone: the runner itself must stop its LIBERO workers (SLURM signals them all).
    process, stderr = interrupt_after_an_episode(tmp_path, lambda process: os.kill(process.pid, signal.SIGTERM))
    assert process.returncode == 143
    with pytest.raises(ProcessLookupError):  # no worker left in the cell's process group
        os.killpg(process.pid, 0)
    assert "Traceback" not in stderr
    done, folder = episodes(tmp_path), cell_folder(tmp_path)
    assert 1 <= done < 3 and not (folder / "episodes.parquet").exists()
    message = (f"vqb rollout: terminated (SIGTERM): {REF} has {done} of 3 episodes recorded in {folder}; "
               "run the same command again to resume it")
    assert stderr.splitlines().count(message) == 1, stderr[-2000:]

    subprocess.run(rollout(tmp_path), check=True, timeout=900, capture_output=True)
    two_writers.finished()
    uninterrupted = cell_folder(two_writers.results)
    assert outcomes(folder) == outcomes(uninterrupted) and len(outcomes(folder)) == 3
    frames = [pd.read_parquet(f / "episodes.parquet") for f in (folder, uninterrupted)]
    resumed, reference = (f.drop(columns=[c for c in TIMING_FIELDS if c in f.columns]) for f in frames)
    assert resumed.equals(reference)


def test_a_second_writer_of_a_running_cell_is_refused_naming_the_first_which_completes_alone(two_writers):
    second, folder = two_writers.second, cell_folder(two_writers.results)
    assert two_writers.alive_then  # refused while the first still ran
    assert second.returncode == 2, second.stderr[-2000:]
    assert second.stderr.startswith(f"vqb rollout: error: cell {REF}: another process writes it: {folder / 'writer.lock'} "
                                    f"is locked by pid {two_writers.first.pid} on host ")
    assert f"writing cell {REF}" in second.stderr and len(second.stderr.strip().splitlines()) == 1
    # Refused at its start, before any model load (the first spends longer loading its own).
    assert two_writers.refused_after < 60
    first_stderr = two_writers.finished()
    assert two_writers.first.returncode == 0, first_stderr[-2000:]
    lines = [json.loads(line) for line in (folder / "journal.jsonl").read_text().splitlines()]
    assert [line["kind"] for line in lines].count("header") == 1
    assert len([line for line in lines if line["kind"] == "episode"]) == len(outcomes(folder)) == 3
    assert len(pd.read_parquet(folder / "episodes.parquet")) == 3
