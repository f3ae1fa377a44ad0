"""The committed trained checkpoint (checkpoints/pi05_metaworld, rule train_policy) through the rollout
path on the CPU: the download rule's offline resolution, the adapter's released-checkpoint loader and
one action chunk for a Meta-World observation."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from vlaquantbench.hub.cache import offline_cache

HOME = Path(__file__).resolve().parents[1] / "checkpoints" / "pi05_metaworld"
TRAINING = json.loads((HOME / "training.json").read_text())
MAX_WEIGHTS_BYTES = 40_000_000


@pytest.fixture(scope="module")
def adapter(tmp_path_factory):
    from vlaquantbench.models.adapter import AdapterConfig, make_adapter
    from vlaquantbench.runner.checkpoint import download_checkpoint

    stamp = tmp_path_factory.mktemp("checkpoint") / "checkpoint.json"
    with offline_cache(HOME):
        info = download_checkpoint("pi05", "full", TRAINING["checkpoint"], TRAINING["revision"], stamp)
        adapter = make_adapter(AdapterConfig(model="pi05", variant="full", checkpoint=TRAINING["checkpoint"],
                                             revision=TRAINING["revision"], checkpoint_dir=info["path"],
                                             executed_chunk=TRAINING["policy"]["n_action_steps"]))
        adapter.load()
    return adapter


def test_the_committed_weights_are_small_and_at_their_content_hash():
    from vlaquantbench.training import weights_revision

    weights = HOME / "hub" / "models--vlaquantbench--pi05-metaworld-scripted" / "snapshots" / TRAINING["revision"] / "model.safetensors"
    assert weights.stat().st_size <= MAX_WEIGHTS_BYTES
    assert weights_revision(weights) == TRAINING["revision"]


def test_it_loads_with_the_released_architectures_scopes_and_its_provenance(adapter):
    from vlaquantbench.quant import select_layers

    provenance = adapter.checkpoint_provenance
    assert provenance["tokenizer"]["repo"] == TRAINING["tokenizer"]["repo"]
    assert provenance["widths"] == "reduced (trained here)"
    assert provenance["training"]["dataset_manifest_sha256"] == TRAINING["dataset"]["manifest_sha256"]
    assert provenance["normalization"]["policy_postprocessor"]["state_files"]
    # The paper's per-component linear-layer counts (tab:vla_params), layer for layer.
    counts = select_layers(adapter.model, adapter.components, "e2e", None, None).counts()
    assert {c: v["layers"] for c, v in counts.items()} == {"ve": 162, "mp": 1, "llm": 126, "ah": 167}
    assert adapter.predicted_chunk == TRAINING["policy"]["chunk_size"]


def test_it_acts_on_a_metaworld_observation(adapter):
    size = adapter.policy_config.image_resolution[0]
    rng = np.random.default_rng(0)
    observation = {"image": rng.integers(0, 256, (size, size, 3), dtype=np.uint8),
                   "state": np.array([0.0, 0.6, 0.2, 1.0]), "instruction": TRAINING["dataset"]["tasks"][0]}
    actions = adapter.act([observation], [adapter.reset(0)])
    assert actions.shape == (1, TRAINING["policy"]["chunk_size"], 4) and np.isfinite(actions).all()
