"""A study model entry naming a checkpoint trained here: `study.models.<model>.trained: <home folder>`.

Rule train_policy (`vlaquantbench.training`) writes the checkpoint as a plain folder:

    <home>/training.json     provenance: checkpoint name and revision, tokenizer, dataset, steps, and
                             `files`, the SHA-256 of every file below policy/ and tokenizer/
    <home>/policy/           the policy's and its processors' `save_pretrained` files
    <home>/tokenizer/        the task tokenizer its preprocessor names (`save_pretrained`)

The revision is the SHA-1 of `policy/model.safetensors` (a hub commit id's 40 hex digits). `verify`
checks the folder against training.json before anything reads it: the weights against the revision,
every recorded file against its SHA-256, and no file unrecorded. It runs when the DAG is built, in the
checkpoint job and in the adapter that loads the policy, so a changed file (a sign-flipped but valid
weights file, an edited config) is refused naming it, instead of loading under the old revision.

When the DAG is built, `trained_weights` resolves the entry into what a released checkpoint's entry says
by hand (the checkpoint and its pinned revision) plus what the training fixed and a cell must run with:
the executed chunk (`n_action_steps`) and the camera size (the policy's input resolution, from its lerobot
`config.json`). All of it enters the hashed cell config. No torch or lerobot import: the DAG is built
from these.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING, Any

from vlaquantbench.errors import UserError

if TYPE_CHECKING:
    from vlaquantbench.config.study import ModelWeights

TRAINING_FILE = "training.json"
POLICY_DIR = "policy"
TOKENIZER_DIR = "tokenizer"
WEIGHTS_FILE = "model.safetensors"
# lerobot's saved policy config: its `type` names the policy class (pi05, pi0, ...)
POLICY_CONFIG_FILE = "config.json"


def training_file(home: str | Path) -> Path:
    return Path(home) / TRAINING_FILE


def policy_folder(home: str | Path) -> Path:
    return Path(home) / POLICY_DIR


def tokenizer_folder(home: str | Path) -> Path:
    return Path(home) / TOKENIZER_DIR


def _digests(path: Path) -> tuple[str, str]:
    """SHA-1 and SHA-256 of a file, in one read."""
    sha1, sha256 = hashlib.sha1(), hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            sha1.update(block)
            sha256.update(block)
    return sha1.hexdigest(), sha256.hexdigest()


def recorded_files(home: str | Path) -> dict[str, str]:
    """{path below `home`: SHA-256} of every file in its policy and tokenizer folders, as training.json records them."""
    home = Path(home)
    found = sorted(p for folder in (POLICY_DIR, TOKENIZER_DIR) for p in (home / folder).rglob("*") if p.is_file())
    return {p.relative_to(home).as_posix(): _digests(p)[1] for p in found}


def read_training(home: str | Path, field: str) -> dict[str, Any]:
    """`<home>/training.json`; UserError naming `field` and the file when it is missing or incomplete."""
    provenance = training_file(home)
    if not provenance.is_file():
        raise UserError(f"{field}: {home}: no {TRAINING_FILE}: train the checkpoint first (snakemake {provenance} "
                        "--configfile <the config whose `training` section writes it>)")
    try:
        training = json.loads(provenance.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise UserError(f"{field}: {provenance} is not JSON ({err})") from None
    missing = [key for key in ("checkpoint", "revision", "policy", "tokenizer", "files") if key not in training]
    if missing:
        raise UserError(f"{field}: {provenance} records no {', '.join(missing)} (not written by rule train_policy?)")
    return training


def verify(home: str | Path, field: str = "trained checkpoint") -> dict[str, Any]:
    """The training.json of `home` after checking the folder against it (module doc); UserError naming the
    file, the checkpoint and its revision on the first difference."""
    home = Path(home)
    training = read_training(home, field)
    named = f"{field}: {training['checkpoint']}@{training['revision']} ({home})"
    weights = policy_folder(home) / WEIGHTS_FILE
    if not weights.is_file():
        raise UserError(f"{named}: {weights} is missing")
    sha1, _ = _digests(weights)
    if sha1 != training["revision"]:
        raise UserError(f"{named}: {weights} is not the weights of this revision (its SHA-1 is {sha1}): "
                        "restore the file or retrain")
    recorded = training["files"]
    found = recorded_files(home)
    for name in sorted(set(recorded) | set(found)):
        if name not in found:
            raise UserError(f"{named}: {home / name} is recorded in {TRAINING_FILE} but missing")
        if name not in recorded:
            raise UserError(f"{named}: {home / name} is not recorded in {TRAINING_FILE}: remove it or retrain")
        if found[name] != recorded[name]:
            raise UserError(f"{named}: {home / name} has SHA-256 {found[name]}, but {TRAINING_FILE} records "
                            f"{recorded[name]}: restore the file or retrain")
    return training


@lru_cache(maxsize=None)
def _read(home: str, field: str) -> dict[str, Any]:
    """training.json and the policy config of `home`, verified; UserError naming `field` and the file."""
    training = verify(home, field)
    return {"training": training, "policy": json.loads((policy_folder(home) / POLICY_CONFIG_FILE).read_text())}


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
