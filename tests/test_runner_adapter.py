"""pi-family adapters on the real lerobot architectures (demo variant: reduced widths, random weights)."""

import dataclasses
import re
from pathlib import Path

import numpy as np
import pytest

from vlaquantbench.errors import UserError
from vlaquantbench.models.adapter import AdapterConfig, PolicyAdapter, make_adapter


def observations(n, size=64, seed=0):
    rng = np.random.default_rng(seed)
    return [
        {
            "agentview": rng.integers(0, 256, (size, size, 3), dtype=np.uint8),
            "wrist": rng.integers(0, 256, (size, size, 3), dtype=np.uint8),
            "state": rng.normal(size=8).astype(np.float32),
            "instruction": f"pick up the black bowl number {i} and place it on the plate",
        }
        for i in range(n)
    ]


@pytest.fixture(scope="module", params=["pi05", "pi0"])
def adapter(request):
    adapter = make_adapter(AdapterConfig(model=request.param, variant="demo", flow_steps=3))
    adapter.load()
    return adapter


def test_adapter_protocol_and_chunk_lengths(adapter):
    assert isinstance(adapter, PolicyAdapter)
    assert (adapter.predicted_chunk, adapter.executed_chunk) == (50, 10)
    assert set(adapter.components) == {"ve", "mp", "llm", "ah"}
    chunk = adapter.act(observations(2), [adapter.reset(1), adapter.reset(2)])
    assert chunk.shape == (2, 50, 7) and chunk.dtype == np.float32 and np.isfinite(chunk).all()


def test_actions_do_not_depend_on_the_batch(adapter):
    """CPU float32: an episode's chunk is bit-identical alone or in a batch of four."""
    obs = observations(4)
    seeds = [0, 1009, 2018, 7]
    batched = adapter.act(obs, [adapter.reset(s) for s in seeds])
    alone = np.concatenate([adapter.act([o], [adapter.reset(s)]) for o, s in zip(obs, seeds)])
    assert np.array_equal(batched, alone)
    # ... and the episode's own stream matters: another seed gives other flow noise, other actions.
    other = adapter.act(obs[:1], [adapter.reset(seeds[0] + 1)])
    assert not np.array_equal(other[0], alone[0])


def test_executed_chunk_longer_than_predicted_is_refused():
    adapter = make_adapter(AdapterConfig(model="pi05", variant="demo", executed_chunk=51))
    with pytest.raises(UserError, match="executed chunk 51 must lie in 1..50"):
        adapter.load()


def test_full_variant_without_a_snapshot_names_the_checkpoint():
    adapter = make_adapter(AdapterConfig(model="pi05", variant="full", checkpoint="lerobot/pi05_libero_finetuned_v044"))
    with pytest.raises(UserError, match="lerobot/pi05_libero_finetuned_v044"):
        adapter.load()


def test_the_adapter_reads_cameras_by_the_roles_the_config_declares(adapter):
    """The same images under other observation keys, declared as the main and wrist cameras (a benchmark's
    `cameras`), give the same chunk: the adapter maps roles to the checkpoint's features, not names; the
    cameras swapped give another chunk."""
    obs, config = observations(1), adapter.config
    expected = adapter.act(obs, [adapter.reset(3)])
    renamed = [{"front": o["agentview"], "hand": o["wrist"], "state": o["state"], "instruction": o["instruction"]}
               for o in obs]
    try:
        adapter.config = dataclasses.replace(config, cameras={"main": "front", "wrist": "hand"})
        assert np.array_equal(adapter.act(renamed, [adapter.reset(3)]), expected)
        adapter.config = dataclasses.replace(config, cameras={"main": "hand", "wrist": "front"})
        assert not np.array_equal(adapter.act(renamed, [adapter.reset(3)]), expected)
        adapter.config = dataclasses.replace(config, cameras={"main": "side"})
        with pytest.raises(UserError, match=r"feed none of the checkpoint's cameras"):
            adapter.act(renamed, [adapter.reset(3)])
    finally:
        adapter.config = config


def test_no_adapter_reads_an_observation_by_a_benchmarks_camera_key():
    from vlaquantbench.envs.registry import BENCHMARK_SUITES, CAMERA_ROLES, get_benchmark
    from vlaquantbench.models.pi_family_adapter import ROLE_FEATURES

    keys = {key for name in BENCHMARK_SUITES for key in get_benchmark(name).cameras.values()}
    models = Path(__file__).parents[1] / "src" / "vlaquantbench" / "models"
    for path in [*models.glob("*adapter.py"), *models.glob("*/adapter.py")]:
        source = path.read_text()
        for key in keys:
            assert not re.search(rf"""\b(obs|observation)\[\s*["']{key}["']""", source), (path, key)
    assert set(ROLE_FEATURES) == set(CAMERA_ROLES)
