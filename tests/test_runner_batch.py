"""Two real LIBERO episodes run as one batch of two and one at a time give identical actions and outcomes,
for every model with an adapter (demo policies of the real architectures). The batched run holds ready
slots for a batch of two (`min_batch`), so every one of its policy calls really is a batch of two."""

import contextlib
import time
from collections import defaultdict

import mujoco
import numpy as np
import pytest

from vlaquantbench.envs.libero import LiberoSuite, LiberoVectorEnv
from vlaquantbench.models.adapter import AdapterConfig, make_adapter
from vlaquantbench.quant import QuantConfig, quantize_
from vlaquantbench.runner.loop import run_episodes

pytestmark = pytest.mark.slow


# 12 steps at these executed chunk lengths are two chunks per episode.
MODELS = {"pi05": 10, "xvla": 10, "openvla_oft": 8}


@pytest.fixture(scope="module")
def libero_envs():
    """(suite, env(num_envs, control_mode)): LIBERO vector envs kept across the models' cases, one per slot count
    and control mode, so a model whose client steps the arm as an earlier one's does runs on the same workers (an
    episode depends on its start, not on what the worker ran before: tests/test_libero_env.py)."""
    suite = LiberoSuite("libero_spatial")
    with contextlib.ExitStack() as stack:
        envs = {}

        def env(num_envs, control_mode):
            if (num_envs, control_mode) not in envs:
                # X-VLA's client pins MuJoCo 3.1.6; this environment has 3.3.2 (cells record that as an override).
                envs[num_envs, control_mode] = stack.enter_context(LiberoVectorEnv(
                    suite, num_envs, camera_size=64, control_mode=control_mode, mujoco=mujoco.__version__))
            return envs[num_envs, control_mode]

        yield suite, env


@pytest.mark.parametrize("model", sorted(MODELS))
def test_batch_of_two_equals_batch_of_one(model, libero_envs):
    suite, libero_env = libero_envs
    specs = [suite.episode_spec(0, 0), suite.episode_spec(1, 0)]
    adapter = make_adapter(AdapterConfig(model=model, variant="demo", flow_steps=2, executed_chunk=MODELS[model]))
    adapter.load()
    config = QuantConfig.from_preset("W4A4", scope="ah")
    report = quantize_(adapter.model, config, config.select(adapter.model, adapter.components))

    chunks = defaultdict(list)  # episode seed -> [(state observed, chunk predicted)]
    batches = []  # batch size of every policy call
    seconds = defaultdict(list)  # episode seed -> duration of each policy call computing its chunk
    act = adapter.act

    def recording_act(observations, generators):
        batches.append(len(observations))
        began = time.perf_counter()
        out = act(observations, generators)
        for generator in generators:
            seconds[generator.initial_seed()].append(time.perf_counter() - began)
        for obs, generator, chunk in zip(observations, generators, out):
            chunks[generator.initial_seed()].append((obs["state"].copy(), chunk.copy()))
        return out

    adapter.act = recording_act

    def run(num_envs):
        seconds.clear()
        chunks.clear()
        batches.clear()
        records = []
        run_episodes(adapter, libero_env(num_envs, adapter.control_mode), specs, max_steps=12,
                     on_finished=records.extend, min_batch=2)
        return sorted(records, key=lambda r: r["task_id"]), {seed: list(calls) for seed, calls in chunks.items()}

    batched, batched_chunks = run(2)
    assert batches == [2, 2]  # two chunks per episode, each call the pair
    single, single_chunks = run(1)  # one slot: each call as soon as it is ready, nothing else stepping
    assert batches == [1, 1, 1, 1]
    # The authors' latency fields: full inference per chunk (the loop's timing encloses the call timed
    # here), the same time per control step, and no CUDA memory on the CPU.
    for record in single:
        calls = seconds[record["seed"]]
        assert len(calls) == 2 and record["inference_latency_mean_s"] >= np.mean(calls) > 0
        assert record["inference_latency_mean_s"] == record["policy_batch_latency_mean_s"]
        assert record["policy_latency_mean_s"] == pytest.approx(2 * record["inference_latency_mean_s"] / record["steps"])
        assert "peak_vram_gb" not in record

    assert [(r["task_id"], r["episode"], r["seed"]) for r in batched] == [(0, 0, 0), (1, 0, 1009)]
    for a, b in zip(batched, single):
        assert (a["success"], a["steps"], a["actions_sha256"]) == (b["success"], b["steps"], b["actions_sha256"])
    assert batched_chunks.keys() == single_chunks.keys() == {0, 1009}
    for seed in batched_chunks:
        assert len(batched_chunks[seed]) == len(single_chunks[seed]) == 2  # 12 steps, 10 (OFT: 8) executed per chunk
        for (state_a, chunk_a), (state_b, chunk_b) in zip(batched_chunks[seed], single_chunks[seed]):
            assert np.array_equal(state_a, state_b)
            assert np.array_equal(chunk_a, chunk_b)
    # The two episodes really differ (different tasks, init states and noise) and the hooks ran.
    assert batched[0]["actions_sha256"] != batched[1]["actions_sha256"]
    assert not report.unfired()
