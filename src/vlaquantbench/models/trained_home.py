"""A study model entry naming a checkpoint trained here: `study.models.<model>.trained: <HF_HOME folder>`.

Rule train_policy (`vlaquantbench.training`) writes the checkpoint into `<home>/hub` in the Hugging Face
cache layout and `<home>/training.json`, which names the checkpoint repository and revision. When the DAG
is built, `trained_weights` resolves the entry into what a released checkpoint's entry says by hand (the
checkpoint and its pinned revision) plus what the training fixed and a cell must run with: the executed
chunk (`n_action_steps`) and the camera size (the policy's input resolution, from the checkpoint's
lerobot `config.json`). All of it enters the hashed cell config. The rollout and calibration jobs load
the checkpoint and its tokenizer offline from `<home>` (`runner.checkpoint.download_checkpoint` records the
folder in the checkpoint stamp). No torch or lerobot import: the DAG is built from these.
"""

from __future__ import annotations

import dataclasses
import json
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING, Any

from vlaquantbench.errors import UserError

if TYPE_CHECKING:
    from vlaquantbench.config.study import ModelWeights

TRAINING_FILE = "training.json"
# lerobot's saved policy config: its `type` names the policy class (pi05, pi0, ...)
POLICY_CONFIG_FILE = "config.json"


def training_file(home: str | Path) -> Path:
    return Path(home) / TRAINING_FILE


@lru_cache(maxsize=None)
def _read(home: str, field: str) -> dict[str, Any]:
    """training.json and the snapshot's policy config of `home`; UserError naming `field` and the file."""
    from vlaquantbench.hub.cache import repo_folder

    provenance = training_file(home)
    if not provenance.is_file():
        raise UserError(f"{field}: {home}: no {TRAINING_FILE}: train the checkpoint first (snakemake {provenance} "
                        "--configfile <the config whose `training` section writes it>)")
    training = json.loads(provenance.read_text())
    missing = [key for key in ("checkpoint", "revision", "policy") if key not in training]
    if missing:
        raise UserError(f"{field}: {provenance} records no {', '.join(missing)} (not written by rule train_policy?)")
    snapshot = repo_folder(Path(home) / "hub", training["checkpoint"]) / "snapshots" / training["revision"]
    config_file = snapshot / POLICY_CONFIG_FILE
    if not config_file.is_file():
        raise UserError(f"{field}: {provenance} names {training['checkpoint']}@{training['revision']}, but {home} "
                        f"holds no snapshot of it ({config_file} is missing)")
    return {"training": training, "policy": json.loads(config_file.read_text())}


def trained_weights(model: str, weights: ModelWeights) -> ModelWeights:
    """`weights` (an entry with `trained` set) with the checkpoint, revision and the runner settings its
    training fixed; the entry's own `runner` settings still win. UserError naming the field on an entry
    that also pins a checkpoint, a variant other than full, or a checkpoint of another model."""
    field = f"study.models.{model}.trained"
    if weights.variant != "full":
        raise UserError(f"{field}: a trained checkpoint runs as variant full, not {weights.variant!r}")
    if weights.checkpoint or weights.revision:
        raise UserError(f"{field}: the checkpoint and revision come from its {TRAINING_FILE}; "
                        f"study.models.{model} must not name them too")
    found = _read(weights.trained, field)
    training, policy = found["training"], found["policy"]
    if policy.get("type") != model:
        raise UserError(f"{field}: {weights.trained} holds a {policy.get('type')!r} checkpoint "
                        f"({training['checkpoint']}@{training['revision']}), not a {model!r} one")
    height, width = policy["image_resolution"]
    if height != width:
        raise UserError(f"{field}: the checkpoint reads {height}x{width} images; the cameras render square ones")
    trained_runner = {"executed_chunk": training["policy"]["n_action_steps"], "camera_size": height}
    return dataclasses.replace(weights, checkpoint=training["checkpoint"], revision=training["revision"],
                               runner={**trained_runner, **weights.runner})
