"""Training a policy from scratch on a LeRobotDataset of demonstrations (the `train_policy` rule).

lerobot's own pieces do the work: the model folder's `trained.build_policy` (lerobot's `make_policy`
and processor factory), `LeRobotDataset` with the action chunk's `delta_timestamps`
(`resolve_delta_timestamps`), lerobot's `EpisodeAwareSampler` in a torch DataLoader as
`lerobot_train` builds it, the policy's loss (`forward`), and its optimizer and scheduler presets.
The loop that drives them is written here because lerobot's `lerobot_train.train` cannot take this
policy: it builds the processors through a factory that loads PaliGemma's tokenizer by name and the
policy at the released widths, and it needs `accelerate` (lerobot's training extra, not in the
project's stack). Its body is `lerobot_train.update_policy`'s without the Accelerator: loss,
backward, gradient clipping at the preset's norm, optimizer and scheduler steps.

The result is an HF_HOME folder holding the checkpoint and its tokenizer as two hub repositories,
the checkpoint at a revision equal to its weights' content hash (SHA-1 of model.safetensors, the
40 hex digits of a hub commit), and a provenance JSON (dataset manifest hash, steps, batch size,
seed, loss curve, wall time, device).
"""

from __future__ import annotations

import hashlib
import importlib
import json
import logging
import math
import tempfile
import time
from pathlib import Path
from typing import Any

from vlaquantbench.atomic import write_text
from vlaquantbench.errors import UserError

LOG = logging.getLogger(__name__)
# Points of the recorded loss curve (means over equal spans of steps).
LOSS_CURVE_POINTS = 50


def weights_revision(weights: Path) -> str:
    """The hub revision of a trained checkpoint: the SHA-1 of its weights file (a commit id's 40 hex digits)."""
    with open(weights, "rb") as f:
        return hashlib.file_digest(f, "sha1").hexdigest()


def _device_record(device) -> dict[str, Any]:
    import torch

    if device.type != "cuda":
        return {"type": device.type}
    return {"type": "cuda", "name": torch.cuda.get_device_name(device), "torch": torch.__version__,
            "cuda": torch.version.cuda}


def train_policy(dataset_root: str | Path, dataset_repo_id: str, dataset_manifest: str | Path, output: str | Path,
                 provenance: str | Path, training: dict[str, Any]) -> dict[str, Any]:
    """Train `training["model"]` (the config's `training` section) on the LeRobotDataset `dataset_repo_id`
    at `dataset_root`; write the HF_HOME folder `output` and the provenance JSON `provenance`; returns
    the provenance."""
    import torch
    from lerobot.datasets.factory import resolve_delta_timestamps
    from lerobot.datasets.lerobot_dataset import LeRobotDataset, LeRobotDatasetMetadata
    from lerobot.datasets.sampler import EpisodeAwareSampler
    from lerobot.utils.utils import cycle

    from vlaquantbench.hub.cache import tree_revision, write_snapshot
    from vlaquantbench.models.paligemma_family import TRAINING_FILE

    dataset_root, output = Path(dataset_root), Path(output)
    if not (dataset_root / "meta" / "info.json").is_file():
        raise UserError(f"training dataset {dataset_root} is not a LeRobotDataset (no meta/info.json)")
    trained = importlib.import_module(f"vlaquantbench.models.{training['model']}.trained")
    tokenizers = importlib.import_module(f"vlaquantbench.models.{training['model']}.task_tokenizer")
    device = torch.device(training["device"])
    torch.manual_seed(training["seed"])
    # TF32 matmuls on the GPU: the float32 weights train at tensor-core speed.
    torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = True

    meta = LeRobotDatasetMetadata(dataset_repo_id, root=dataset_root)
    descriptions = sorted(meta.tasks.index) if hasattr(meta.tasks, "index") else sorted(meta.tasks)
    tokenizer = tokenizers.build_task_tokenizer(descriptions)
    policy, preprocessor, postprocessor, widths = trained.build_policy(
        meta, training["policy"], training["tokenizer_repo"], tokenizer, str(device))
    dataset = LeRobotDataset(dataset_repo_id, root=dataset_root, delta_timestamps=resolve_delta_timestamps(policy.config, meta))
    sampler = EpisodeAwareSampler(meta.episodes["dataset_from_index"], meta.episodes["dataset_to_index"],
                                  episode_indices_to_use=dataset.episodes, shuffle=True, seed=training["seed"],
                                  absolute_to_relative_idx=dataset.absolute_to_relative_idx)
    loader = torch.utils.data.DataLoader(dataset, batch_size=training["batch_size"], sampler=sampler,
                                         num_workers=training["num_workers"], pin_memory=device.type == "cuda",
                                         drop_last=False, persistent_workers=training["num_workers"] > 0)
    optimizer = policy.config.get_optimizer_preset().build(policy.get_optim_params())
    scheduler = policy.config.get_scheduler_preset().build(optimizer, training["steps"])
    clip = policy.config.get_optimizer_preset().grad_clip_norm
    n_params = sum(p.numel() for p in policy.parameters())
    LOG.info("policy: %d parameters; dataset: %d frames, %d episodes, tasks %s", n_params, dataset.num_frames,
             dataset.num_episodes, descriptions)

    policy.train()
    losses: list[float] = []
    start = time.monotonic()
    batches = cycle(loader)
    # A wall-clock bound (the GPU machine's command limit): training stops there, recording the steps it made.
    time_limit_s = training.get("time_limit_s")
    for step in range(1, training["steps"] + 1):
        if time_limit_s is not None and time.monotonic() - start > time_limit_s:
            LOG.warning("time limit %d s reached after %d of %d steps", time_limit_s, step - 1, training["steps"])
            break
        batch = preprocessor(next(batches))
        loss, _ = policy.forward(batch)
        if not math.isfinite(loss.item()):
            raise RuntimeError(f"training loss is {loss.item()} at step {step}")
        loss.backward()
        torch.nn.utils.clip_grad_norm_(policy.parameters(), clip)
        optimizer.step()
        optimizer.zero_grad(set_to_none=True)
        scheduler.step()
        losses.append(loss.item())
        if step % training["log_every"] == 0 or step == 1:
            LOG.info("step %d/%d loss %.4f lr %.2e (%.1f s)", step, training["steps"], loss.item(),
                     scheduler.get_last_lr()[0], time.monotonic() - start)
    wall_s = time.monotonic() - start

    policy.eval()
    hub = output / "hub"
    with tempfile.TemporaryDirectory() as scratch:
        tokenizer_folder = tokenizers.write_task_tokenizer(Path(scratch) / "tokenizer", descriptions)
        tokenizer_revision = tree_revision(tokenizer_folder)
        write_snapshot(hub, training["tokenizer_repo"], tokenizer_revision, tokenizer_folder)
        folder = trained.save(Path(scratch) / "checkpoint", policy.to("cpu"), preprocessor, postprocessor, widths)
        revision = weights_revision(folder / "model.safetensors")
        record = _provenance(training, revision, folder, n_params, tokenizer, tokenizer_revision, descriptions,
                             dataset_root, dataset_repo_id, dataset_manifest, dataset, losses, wall_s, device)
        # The snapshot carries it too: the rollout path's headers cite it (PiFamilyAdapter).
        write_text(folder / TRAINING_FILE, json.dumps(record, indent=2) + "\n")
        write_snapshot(hub, training["checkpoint_repo"], revision, folder)
    write_text(provenance, json.dumps(record, indent=2) + "\n")
    return record


def _provenance(training, revision, folder, n_params, tokenizer, tokenizer_revision, descriptions, dataset_root,
                dataset_repo_id, dataset_manifest, dataset, losses, wall_s, device) -> dict[str, Any]:
    from vlaquantbench.hub.checks import sha256

    span = max(1, len(losses) // LOSS_CURVE_POINTS)
    return {
        "checkpoint": training["checkpoint_repo"], "revision": revision,
        "weights_bytes": (folder / "model.safetensors").stat().st_size, "parameters": n_params,
        "tokenizer": {"repo": training["tokenizer_repo"], "revision": tokenizer_revision, "vocabulary": len(tokenizer),
                      "source": "word-level tokenizer built from the dataset's task descriptions "
                                "(vlaquantbench.models.pi05.task_tokenizer)"},
        "dataset": {"root": str(dataset_root), "repo_id": dataset_repo_id, "manifest_sha256": sha256(dataset_manifest),
                    "frames": dataset.num_frames, "episodes": dataset.num_episodes, "tasks": descriptions},
        "steps": len(losses), "planned_steps": training["steps"], "batch_size": training["batch_size"],
        "seed": training["seed"],
        "policy": training["policy"],
        "loss_curve": {"span_steps": span,
                       "mean_loss": [round(sum(losses[i:i + span]) / len(losses[i:i + span]), 5)
                                     for i in range(0, len(losses), span)]},
        "wall_s": round(wall_s, 1), "device": _device_record(device),
    }
