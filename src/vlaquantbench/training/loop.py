"""Training a policy from scratch on a LeRobotDataset of demonstrations (the `train_policy` rule).

lerobot's own pieces do the work: the model folder's `trained.build_policy` (lerobot's `make_policy`
and processor factory), the policy's preprocessor (run once per frame, `frames.DeviceFrames`), the
policy's flow-matching loss (`PI05Pytorch.forward`), and its optimizer and scheduler presets. The
loop that drives them is written here because lerobot's `lerobot_train.train` cannot take this
policy: it builds the processors through a factory that loads PaliGemma's tokenizer by name and the
policy at the released widths, and it needs `accelerate` (lerobot's training extra, not in the
project's stack). Its step is `lerobot_train.update_policy`'s without the Accelerator: loss,
backward, gradient clipping at the preset's norm, optimizer and scheduler steps.

Speed (benchmarks/gpu_train_policy.sh measures it): the whole dataset sits on the device
(`DeviceFrames`), the forward runs under bf16 autocast when `precision: bfloat16`, and no step waits
for the device: losses stay on it until a log line (every `log_every` steps) reads them, and a
non-finite loss is refused there.

Resumable: at `time_limit_s` the run saves `<output>/resume/state.pt` (weights, optimizer, scheduler,
step, every random stream; the sampler's position is a function of the seed and the step) and stops
with a UserError saying so; the same command continues from it, and the result equals one
uninterrupted run's (tests/test_training.py). The state is bound to the dataset and the settings that
made it: another dataset or section is refused by name.

The result is a plain folder (`models.trained_home`): the policy's `save_pretrained` files, its task
tokenizer's, and `training.json`, the provenance (a revision equal to the weights' content hash, the
SHA-1 of model.safetensors: the 40 hex digits of a hub commit; dataset manifest hash, steps, batch size,
seed, loss curve, wall time, device; every file's SHA-256).
"""

from __future__ import annotations

import hashlib
import importlib
import json
import logging
import random
import tempfile
import time
from pathlib import Path
from typing import Any

from vlaquantbench.atomic import write_text
from vlaquantbench.errors import UserError
from vlaquantbench.training.config import TrainingConfig

LOG = logging.getLogger(__name__)
# Points of the recorded loss curve (means over equal spans of steps).
LOSS_CURVE_POINTS = 50
RESUME_DIR = "resume"
STATE_FILE = "state.pt"
# Settings a saved state must share with the run that resumes it (time_limit_s and log_every may change).
STATE_BINDING = ("model", "seed", "steps", "batch_size", "precision", "random_shift_px", "policy")
# `compile_mode` and `cuda_graph` may change between a run and its resumption: they compute the same function.


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


class TrainingPaused(UserError):
    """The time limit came before the planned steps; the state to resume from is saved."""


def _epoch_order(frames: int, seed: int, epoch: int, device):
    """The sampler: epoch e visits every frame once in an order drawn from (seed, epoch) alone, so a
    resumed run finds its place from the step count."""
    import torch

    generator = torch.Generator().manual_seed(seed * 1_000_003 + epoch)
    return torch.randperm(frames, generator=generator).to(device)


def _rng_state(device) -> dict[str, Any]:
    import numpy as np
    import torch

    state = {"python": random.getstate(), "numpy": np.random.get_state(), "torch": torch.get_rng_state()}
    if device.type == "cuda":
        state["cuda"] = torch.cuda.get_rng_state(device)
    return state


def _set_rng_state(state: dict[str, Any], device) -> None:
    import numpy as np
    import torch

    random.setstate(state["python"])
    np.random.set_state(state["numpy"])
    torch.set_rng_state(state["torch"])
    if device.type == "cuda":
        torch.cuda.set_rng_state(state["cuda"], device)


def _binding(training: TrainingConfig, dataset_digest: str) -> dict[str, Any]:
    return {"dataset": dataset_digest, **{key: getattr(training, key) for key in STATE_BINDING}}


def _dataset_digest(frames) -> str:
    """What the training reads of the dataset (images, tokens, action chunks), hashed: a state resumes
    only on the same frames, whatever bytes the files hold."""
    digest = hashlib.sha256()
    for tensor in (frames.images, frames.tokens, frames.attention_mask, frames.actions):
        digest.update(tensor.cpu().contiguous().numpy().tobytes())
    return digest.hexdigest()


def compile_policy(policy, mode: str | None) -> None:
    """`torch.compile` the policy's loss computation (`PI05Pytorch.forward`; its backward through AOTAutograd)
    as lerobot's own `compile_model` switch does at construction, with `mode` (None: eager). Applied to the
    built policy so that the saved config keeps `compile_model` off for the rollouts that load it."""
    import torch

    if mode is None:
        return
    torch.set_float32_matmul_precision("high")  # as lerobot's switch sets it
    policy.model.forward = torch.compile(policy.model.forward, mode=mode)


def _flow_sample(policy, batch):
    """The flow-matching noise and time of a batch, from the policy's own samplers (lerobot draws the
    time on the host: outside a captured graph)."""
    from lerobot.utils.constants import ACTION

    batch_size, chunk = batch[ACTION].shape[:2]
    device = batch[ACTION].device
    return (policy.model.sample_noise((batch_size, chunk, policy.config.max_action_dim), device),
            policy.model.sample_time(batch_size, device))


def _flow_loss(policy, batch, noise, time_, autocast_dtype):
    """`PI05Policy.forward`'s loss without its host reads (it copies the per-dimension loss to the CPU
    and calls `.item()` every step, which waits for the device)."""
    import torch
    from lerobot.utils.constants import OBS_LANGUAGE_ATTENTION_MASK, OBS_LANGUAGE_TOKENS

    device_type = batch[OBS_LANGUAGE_TOKENS].device.type
    # No autocast weight cache: a captured graph must not keep casts made outside it.
    with torch.autocast(device_type, dtype=autocast_dtype, enabled=autocast_dtype is not None, cache_enabled=False):
        images, img_masks = policy._preprocess_images(batch)
        actions = policy.prepare_action(batch)
        losses = policy.model.forward(images, img_masks, batch[OBS_LANGUAGE_TOKENS], batch[OBS_LANGUAGE_ATTENTION_MASK],
                                      actions, noise, time_)
    dims = policy.config.output_features["action"].shape[0]
    return losses[:, :, :dims].float().mean()


def _policy_loss(policy, batch, autocast_dtype):
    """The eager step's loss: noise and time drawn, then `_flow_loss`."""
    return _flow_loss(policy, batch, *_flow_sample(policy, batch), autocast_dtype)


class TrainingStep:
    """One optimization step as `lerobot_train.update_policy` takes it (loss, backward, clipping at the
    preset's norm, optimizer, scheduler), eager or with the loss and gradients replayed from a CUDA
    graph (`captured.CapturedLoss`); returns the loss, left on the device."""

    def __init__(self, policy, optimizer, scheduler, clip_norm: float, autocast_dtype, cuda_graph: bool = False):
        import functools

        from vlaquantbench.training.captured import CapturedLoss

        self.policy, self.optimizer, self.scheduler, self.clip_norm = policy, optimizer, scheduler, clip_norm
        self.autocast_dtype = autocast_dtype
        loss_fn = functools.partial(_flow_loss, autocast_dtype=autocast_dtype)
        self.captured = CapturedLoss(policy, loss_fn) if cuda_graph else None

    def __call__(self, batch, noise=None, time_=None):
        """One step on `batch`; the flow's noise and time are drawn here unless given (as a comparison of two
        steps on the same inputs gives them)."""
        import torch

        if noise is None or time_ is None:
            noise, time_ = _flow_sample(self.policy, batch)
        if self.captured is None:
            loss = _flow_loss(self.policy, batch, noise, time_, self.autocast_dtype)
            loss.backward()
        else:
            loss = self.captured(batch, noise, time_)  # the replay wrote the gradients
        torch.nn.utils.clip_grad_norm_(self.policy.parameters(), self.clip_norm)
        self.optimizer.step()
        if self.captured is None:  # a captured backward writes its gradients anew at each replay
            self.optimizer.zero_grad(set_to_none=True)
        self.scheduler.step()
        return loss.detach()


def train_policy(dataset_root: str | Path, dataset_repo_id: str, dataset_manifest: str | Path,
                 training: TrainingConfig) -> dict[str, Any]:
    """Train `training.model` (the config's `training` section) on the LeRobotDataset `dataset_repo_id`
    at `dataset_root`; write the checkpoint folder `training.output` (its provenance in training.json there);
    returns the provenance. TrainingPaused at `time_limit_s` before `steps` (state saved; run again to resume)."""
    # The time limit counts from here: a call's budget covers loading the dataset too (45 s for 67,662 frames).
    job_started = time.monotonic()
    import torch
    from lerobot.datasets.lerobot_dataset import LeRobotDataset, LeRobotDatasetMetadata

    from vlaquantbench.training.frames import DeviceFrames

    dataset_root, output = Path(dataset_root), Path(training.output)
    if not (dataset_root / "meta" / "info.json").is_file():
        raise UserError(f"training dataset {dataset_root} is not a LeRobotDataset (no meta/info.json)")
    trained = importlib.import_module(f"vlaquantbench.models.{training.model}.trained")
    tokenizers = importlib.import_module(f"vlaquantbench.models.{training.model}.task_tokenizer")
    cuda_graph = training.cuda_graph
    if cuda_graph and training.compile_mode:
        raise UserError("training.cuda_graph and training.compile_mode each speed the step up: set one of them")
    device = torch.device(training.device)
    if cuda_graph and device.type != "cuda":
        raise UserError(f"training.cuda_graph: true needs a CUDA device; training.device is {training.device!r}")
    if device.type == "cuda" and not torch.cuda.is_available():
        raise UserError(f"training.device: {training.device!r}, but torch finds no CUDA device on this machine")
    precision = training.precision
    autocast_dtype = {"float32": None, "bfloat16": torch.bfloat16}[precision]
    seed, batch_size = training.seed, training.batch_size
    torch.manual_seed(seed)
    # TF32 matmuls on the GPU: what float32 work runs at tensor-core speed.
    torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = True

    loading = time.monotonic()
    meta = LeRobotDatasetMetadata(dataset_repo_id, root=dataset_root)
    descriptions = sorted(meta.tasks.index) if hasattr(meta.tasks, "index") else sorted(meta.tasks)
    tokenizer = tokenizers.build_task_tokenizer(descriptions)
    policy, preprocessor, postprocessor, widths = trained.build_policy(
        meta, training.policy, training.tokenizer_repo, tokenizer, str(device))
    if meta.total_frames < batch_size:  # before the dataset is loaded onto the device
        raise UserError(f"training.batch_size {batch_size} is larger than the dataset's {meta.total_frames} frames")
    compile_policy(policy, training.compile_mode)
    dataset = LeRobotDataset(dataset_repo_id, root=dataset_root)
    frames = DeviceFrames(dataset, preprocessor, policy.config.chunk_size, device)
    LOG.info("dataset on %s in %.1f s: %d frames, %d episodes, %s images", device, time.monotonic() - loading,
             len(frames), dataset.num_episodes, tuple(frames.images.shape[1:]))
    optimizer = policy.config.get_optimizer_preset().build(policy.get_optim_params())
    scheduler = policy.config.get_scheduler_preset().build(optimizer, training.steps)
    clip = policy.config.get_optimizer_preset().grad_clip_norm
    n_params = sum(p.numel() for p in policy.parameters())
    LOG.info("policy: %d parameters, %s, batch %d; tasks %s", n_params, precision, batch_size, descriptions)

    state_file = output / RESUME_DIR / STATE_FILE
    step, losses, wall_s = 0, [], 0.0
    if state_file.is_file():
        # On the CPU: generator states must stay CPU byte tensors, and AdamW's step counts CPU scalars (on the
        # device, each step of the non-capturable AdamW reads them back: 16 instead of 23.6 steps a second).
        # load_state_dict moves weights and moments to the parameters' device.
        state = torch.load(state_file, map_location="cpu", weights_only=False)
        binding = _binding(training, _dataset_digest(frames))  # hashing the frames costs a copy: only to resume
        if state["binding"] != binding:
            changed = sorted(k for k in state["binding"] if state["binding"][k] != binding[k])
            raise UserError(f"{state_file}: saved by a run with other {', '.join(changed)}; delete it to start over")
        policy.load_state_dict(state["policy"])
        optimizer.load_state_dict(state["optimizer"])
        scheduler.load_state_dict(state["scheduler"])
        step, losses, wall_s = state["step"], state["losses"], state["wall_s"]
        _set_rng_state(state["rng"], device)
        LOG.info("resuming at step %d of %d from %s", step, training.steps, state_file)

    policy.train()
    train_step = TrainingStep(policy, optimizer, scheduler, clip, autocast_dtype, cuda_graph)
    per_epoch = len(frames) // batch_size  # the last incomplete batch of an epoch is dropped
    shift_px = training.random_shift_px
    pending: list = []  # this span's losses, still on the device
    started = time.monotonic()
    time_limit_s = training.time_limit_s
    order, order_epoch = None, -1
    logged = started  # when the last log line read the device
    first_step = step  # every run takes at least one step, so that a call too short to train still progresses
    while step < training.steps:
        if time_limit_s is not None and step > first_step and time.monotonic() - job_started > time_limit_s:
            wall_s += time.monotonic() - started
            losses += [float(x) for x in torch.stack(pending).tolist()] if pending else []
            state_file.parent.mkdir(parents=True, exist_ok=True)
            torch.save({"binding": _binding(training, _dataset_digest(frames)), "policy": policy.state_dict(),
                        "optimizer": optimizer.state_dict(), "scheduler": scheduler.state_dict(), "step": step,
                        "losses": losses, "wall_s": wall_s, "rng": _rng_state(device)}, state_file)
            raise TrainingPaused(f"training.time_limit_s {time_limit_s}: stopped after step {step} of "
                                 f"{training.steps}; the state is saved in {state_file}: run the same command "
                                 "again to resume")
        epoch, position = divmod(step, per_epoch)
        if epoch != order_epoch:
            order, order_epoch = _epoch_order(len(frames), seed, epoch, device), epoch
        batch = frames.batch(order[position * batch_size:(position + 1) * batch_size], shift_px)
        pending.append(train_step(batch))
        step += 1
        if step % training.log_every == 0 or step == training.steps:
            span = torch.stack(pending).tolist()  # the one wait for the device in `log_every` steps
            pending = []
            losses += span
            if not all(map(_finite, span)):
                raise RuntimeError(f"training loss is not finite within steps {step - len(span) + 1}..{step}")
            now = time.monotonic()
            LOG.info("step %d/%d loss %.4f lr %.2e (%.1f s, %.2f steps/s)", step, training.steps, span[-1],
                     scheduler.get_last_lr()[0], wall_s + now - started, len(span) / (now - logged))
            logged = now
    wall_s += time.monotonic() - started

    record = _write_checkpoint(policy, preprocessor, postprocessor, widths, tokenizer, descriptions, training,
                               {"root": str(dataset_root), "repo_id": dataset_repo_id, "manifest": dataset_manifest,
                                            "frames": dataset.num_frames, "episodes": dataset.num_episodes},
                               losses, wall_s, _device_record(device))
    if state_file.is_file():
        state_file.unlink()
    return record


def checkpoint_from_saved_state(dataset_root: str | Path, dataset_repo_id: str, dataset_manifest: str | Path,
                                training: TrainingConfig, why: str,
                                device_record: dict[str, Any] | None = None) -> dict[str, Any]:
    """End a paused run where its saved state stands (`<training.output>/resume/state.pt`): write the checkpoint of
    its weights as `train_policy` writes a finished run's, with `stopped_early` (the step reached, the
    planned steps, `why`) in the provenance; for when the time to resume is not there. Needs the dataset's
    metadata only (its statistics make the processors); the state must have been saved under `training`'s
    settings. `device_record`: the device the state was trained on (default: recorded as unknown)."""
    import torch
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata

    dataset_root, output = Path(dataset_root), Path(training.output)
    state_file = output / RESUME_DIR / STATE_FILE
    if not state_file.is_file():
        raise UserError(f"{state_file}: no saved state to write a checkpoint from")
    state = torch.load(state_file, map_location="cpu", weights_only=False)
    changed = sorted(k for k in STATE_BINDING if state["binding"].get(k) != getattr(training, k))
    if changed:
        raise UserError(f"{state_file}: saved by a run with other {', '.join(changed)} than this training section")
    trained = importlib.import_module(f"vlaquantbench.models.{training.model}.trained")
    tokenizers = importlib.import_module(f"vlaquantbench.models.{training.model}.task_tokenizer")
    meta = LeRobotDatasetMetadata(dataset_repo_id, root=dataset_root)
    descriptions = sorted(meta.tasks.index) if hasattr(meta.tasks, "index") else sorted(meta.tasks)
    tokenizer = tokenizers.build_task_tokenizer(descriptions)
    policy, preprocessor, postprocessor, widths = trained.build_policy(
        meta, training.policy, training.tokenizer_repo, tokenizer, "cpu")
    policy.load_state_dict(state["policy"])
    stopped = {"at_step": state["step"], "planned_steps": training.steps, "why": why,
               "dataset_digest": state["binding"]["dataset"]}
    record = _write_checkpoint(policy, preprocessor, postprocessor, widths, tokenizer, descriptions, training,
                               {"root": str(dataset_root), "repo_id": dataset_repo_id,
                                            "manifest": dataset_manifest, "frames": meta.total_frames,
                                            "episodes": meta.total_episodes},
                               state["losses"], state["wall_s"], device_record or {"type": "unknown"},
                               stopped_early=stopped)
    state_file.unlink()
    return record


def _write_checkpoint(policy, preprocessor, postprocessor, widths, tokenizer, descriptions, training: TrainingConfig,
                      dataset: dict[str, Any], losses, wall_s, device_record,
                      stopped_early: dict[str, Any] | None = None) -> dict[str, Any]:
    """The plain checkpoint folder `training.output` (`models.trained_home`: policy/, tokenizer/, training.json, whose
    `files` records every file's SHA-256); returns the provenance. A folder of an earlier run is replaced
    whole; training.json is written last, so a folder without it is no checkpoint."""
    import shutil

    from vlaquantbench.hub.cache import tree_revision
    from vlaquantbench.models import trained_home
    from vlaquantbench.models.paligemma_family import TRAINING_FILE

    tokenizers = importlib.import_module(f"vlaquantbench.models.{training.model}.task_tokenizer")
    trained = importlib.import_module(f"vlaquantbench.models.{training.model}.trained")
    policy.eval()
    output = Path(training.output)
    output.mkdir(parents=True, exist_ok=True)
    trained_home.training_file(output).unlink(missing_ok=True)
    with tempfile.TemporaryDirectory(dir=output) as scratch:
        tokenizer_folder = tokenizers.write_task_tokenizer(Path(scratch) / trained_home.TOKENIZER_DIR, descriptions)
        folder = trained.save(Path(scratch) / trained_home.POLICY_DIR, policy.to("cpu"), preprocessor, postprocessor,
                              widths)
        revision = weights_revision(folder / trained_home.WEIGHTS_FILE)
        record = _provenance(training, revision, folder, sum(p.numel() for p in policy.parameters()), tokenizer,
                             tree_revision(tokenizer_folder), descriptions, dataset, losses, wall_s, device_record)
        if stopped_early is not None:
            record["stopped_early"] = stopped_early
        # The policy folder carries the record too: the rollout path's headers cite it (PiFamilyAdapter).
        write_text(folder / TRAINING_FILE, json.dumps(record, indent=2) + "\n")
        for name in (trained_home.POLICY_DIR, trained_home.TOKENIZER_DIR):
            shutil.rmtree(output / name, ignore_errors=True)
            (Path(scratch) / name).rename(output / name)
    record["files"] = trained_home.recorded_files(output)
    write_text(trained_home.training_file(output), json.dumps(record, indent=2) + "\n")
    return record


def _finite(value: float) -> bool:
    return value == value and abs(value) != float("inf")


def _provenance(training: TrainingConfig, revision, folder, n_params, tokenizer, tokenizer_revision, descriptions, dataset,
                losses, wall_s, device_record) -> dict[str, Any]:
    from vlaquantbench.hub.checks import sha256

    span = max(1, len(losses) // LOSS_CURVE_POINTS)
    return {
        "checkpoint": training.checkpoint_repo, "revision": revision,
        "weights_bytes": (folder / "model.safetensors").stat().st_size,
        "weights_sha256": sha256(folder / "model.safetensors"), "parameters": n_params,
        "tokenizer": {"repo": training.tokenizer_repo, "revision": tokenizer_revision, "vocabulary": len(tokenizer),
                      "source": "word-level tokenizer built from the dataset's task descriptions "
                                "(vlaquantbench.models.pi05.task_tokenizer)"},
        "dataset": {"root": dataset["root"], "repo_id": dataset["repo_id"], "manifest_sha256": sha256(dataset["manifest"]),
                    "frames": dataset["frames"], "episodes": dataset["episodes"], "tasks": descriptions},
        "steps": len(losses), "planned_steps": training.steps, "batch_size": training.batch_size,
        "seed": training.seed, "precision": training.precision,
        "random_shift_px": training.random_shift_px, "compile_mode": training.compile_mode,
        "cuda_graph": training.cuda_graph,
        "steps_per_s": round(len(losses) / wall_s, 2) if wall_s else None,
        "policy": training.policy,
        "loss_curve": {"span_steps": span,
                       "mean_loss": [round(sum(losses[i:i + span]) / len(losses[i:i + span]), 5)
                                     for i in range(0, len(losses), span)]},
        "wall_s": round(wall_s, 1), "device": device_record,
    }
