"""The chunk-at-a-time runner on real LIBERO: three episodes over two overlapped slots give exactly the
episodes, chunks and action digests of the per-step runner (one action per round trip, one slot)."""

import hashlib
from collections import defaultdict

import numpy as np
import pytest

from vlaquantbench.envs.libero import LiberoSuite, LiberoVectorEnv
from vlaquantbench.models.adapter import AdapterConfig, make_adapter
from vlaquantbench.quant import QuantConfig, quantize_
from vlaquantbench.runner.loop import run_episodes

pytestmark = pytest.mark.slow

MAX_STEPS = 12  # 10 executed actions per chunk, then a chunk cut at the step limit


def per_step(adapter, env, spec, max_steps):
    """The runner as it was: observe, predict when the chunk is used up, step one action at a time."""
    generator, observation = adapter.reset(spec.seed), env.reset([spec])[0]
    digest, queue, steps, success = hashlib.sha256(), [], 0, False
    while not success and steps < max_steps:
        if not queue:
            queue = list(adapter.act([observation], [generator])[0][: adapter.executed_chunk])
        action = np.asarray(queue.pop(0), np.float64)
        digest.update(action.tobytes())
        observations, successes = env.step(action[None])
        observation, success, steps = observations[0], successes[0], steps + 1
    if not success:
        env.release(0)
    return {"task_id": spec.task_id, "episode": spec.episode, "seed": spec.seed, "success": success, "steps": steps,
            "actions_sha256": digest.hexdigest()}


def test_chunked_overlapped_runner_equals_the_per_step_runner():
    suite = LiberoSuite("libero_spatial")
    specs = [suite.episode_spec(0, 0), suite.episode_spec(1, 0), suite.episode_spec(0, 1)]
    adapter = make_adapter(AdapterConfig(model="pi05", variant="demo", flow_steps=2))
    adapter.load()
    report = quantize_(adapter.model, QuantConfig.from_preset("W4A4", scope="ah"), components=adapter.components)

    chunks = defaultdict(list)  # episode seed -> [(state observed, chunk predicted)]
    act = adapter.act

    def recording_act(observations, generators):
        out = act(observations, generators)
        for obs, generator, chunk in zip(observations, generators, out):
            chunks[generator.initial_seed()].append((obs["state"].copy(), chunk.copy()))
        return out

    adapter.act = recording_act
    key = ("task_id", "episode", "seed", "success", "steps", "actions_sha256")

    with LiberoVectorEnv(suite, 2, camera_size=64) as env:
        records = []
        run_episodes(adapter, env, specs, max_steps=MAX_STEPS, on_finished=records.extend)
    chunked = {r["seed"]: tuple(r[k] for k in key) for r in records}
    chunked_chunks = dict(chunks)

    chunks.clear()
    with LiberoVectorEnv(suite, 1, camera_size=64) as env:
        reference = {spec.seed: tuple(per_step(adapter, env, spec, MAX_STEPS)[k] for k in key) for spec in specs}

    assert chunked == reference
    assert sorted(chunked) == [0, 1, 1009]
    assert all(r["steps"] == MAX_STEPS and not r["nonfinite_action"] for r in records)
    assert chunked_chunks.keys() == chunks.keys()
    for seed in chunks:
        assert len(chunked_chunks[seed]) == len(chunks[seed]) == 2
        for (state_a, chunk_a), (state_b, chunk_b) in zip(chunked_chunks[seed], chunks[seed]):
            assert np.array_equal(state_a, state_b)
            assert np.array_equal(chunk_a, chunk_b)
    # The episodes really differ (tasks, init states and noise) and the hooks ran.
    assert len({r[-1] for r in chunked.values()}) == 3
    assert not report.unfired()
