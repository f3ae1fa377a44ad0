"""Training step rate of the trained pi0.5 (config/trained_study.yaml's `training` section) by precision and
batch size, on the step `vlaquantbench.training` runs: a batch gathered from `DeviceFrames` with the
random shift, `_policy_loss`, backward, clipping, AdamW and the scheduler.

    python benchmarks/gpu_train_step.py --out FILE.json [--config config/trained_study.yaml] [--device cuda]
        [--image-size 112] [--batches 128 256] [--precisions float32 bfloat16] [--compile-modes none default] [--steps 30]

The frames come from a small LeRobotDataset written here (random images at the demonstrations' size);
the step costs the same whatever the pixels. Prints one line a variant and writes `--out` (steps a
second, samples a second, peak memory, and for a compiled step the seconds its first steps took, compiling);
benchmarks/gpu_train_policy.sh reads it to size the run.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
import yaml


def tiny_dataset(root: Path, image_size: int, tasks: list[str], frames: int = 40):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    features = {
        "observation.image": {"dtype": "image", "shape": (image_size, image_size, 3), "names": ["height", "width", "channel"]},
        "observation.state": {"dtype": "float32", "shape": (4,), "names": None},
        "action": {"dtype": "float32", "shape": (4,), "names": None},
    }
    dataset = LeRobotDataset.create("vlaquantbench/step-rate", fps=80, features=features, root=root, use_videos=False)
    rng = np.random.default_rng(0)
    for task in tasks:
        for _ in range(frames):
            dataset.add_frame({"observation.image": rng.integers(0, 256, (image_size, image_size, 3), dtype=np.uint8),
                               "observation.state": rng.uniform(-1, 1, 4).astype(np.float32),
                               "action": rng.uniform(-1, 1, 4).astype(np.float32), "task": task})
        dataset.save_episode()
    dataset.finalize()
    return dataset


def measure(training: dict, image_size: int, device: torch.device, batches: list[int], precisions: list[str],
            steps: int, compile_modes: list[str | None] = (None,)) -> list[dict]:
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from vlaquantbench.models.pi05 import task_tokenizer, trained
    from vlaquantbench.training.frames import DeviceFrames
    from vlaquantbench.training.loop import _policy_loss, compile_policy

    torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = True
    tasks = ["Press a button from the top", "Push and close a drawer"]
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        tiny_dataset(Path(tmp) / "data", image_size, tasks)
        dataset = LeRobotDataset("vlaquantbench/step-rate", root=Path(tmp) / "data")
        tokenizer = task_tokenizer.build_task_tokenizer(tasks)
        variants = [(mode, precision, batch) for mode in compile_modes for precision in precisions for batch in batches]
        for compile_mode, precision, batch_size in variants:
            torch.manual_seed(0)
            policy, preprocessor, _, _ = trained.build_policy(dataset.meta, training["policy"], training["tokenizer_repo"],
                                                              tokenizer, str(device))
            compile_policy(policy, compile_mode)
            frames = DeviceFrames(dataset, preprocessor, policy.config.chunk_size, device)
            optimizer = policy.config.get_optimizer_preset().build(policy.get_optim_params())
            scheduler = policy.config.get_scheduler_preset().build(optimizer, 10_000)
            autocast = {"float32": None, "bfloat16": torch.bfloat16}[precision]
            policy.train()

            def step():
                rows = torch.randint(0, len(frames), (batch_size,), device=device)
                loss = _policy_loss(policy, frames.batch(rows, training.get("random_shift_px", 0)), autocast)
                loss.backward()
                torch.nn.utils.clip_grad_norm_(policy.parameters(), 1.0)
                optimizer.step()
                optimizer.zero_grad(set_to_none=True)
                scheduler.step()
                return loss.detach()

            warming = time.perf_counter()
            torch.stack([step() for _ in range(5)]).sum().item()
            warmup_s = time.perf_counter() - warming
            if device.type == "cuda":
                torch.cuda.synchronize(device)
                torch.cuda.reset_peak_memory_stats(device)
            began = time.perf_counter()
            losses = [step() for _ in range(steps)]
            torch.stack(losses).sum().item()  # waits for the device
            seconds = time.perf_counter() - began
            row = {"compile_mode": compile_mode, "precision": precision, "batch_size": batch_size, "steps": steps,
                   "first_5_steps_s": round(warmup_s, 1),
                   "steps_per_s": round(steps / seconds, 2), "samples_per_s": round(steps * batch_size / seconds),
                   "peak_gib": round(torch.cuda.max_memory_allocated(device) / 2**30, 2) if device.type == "cuda" else None}
            print(json.dumps(row), flush=True)
            results.append(row)
            del policy, optimizer, frames
    return results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", type=Path, default=Path("config/trained_study.yaml"))
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--image-size", type=int, default=None, help="default: the config's demonstrations.image_size")
    parser.add_argument("--batches", type=int, nargs="+", default=[128, 256])
    parser.add_argument("--precisions", nargs="+", default=["float32", "bfloat16"], choices=["float32", "bfloat16"])
    parser.add_argument("--compile-modes", nargs="+", default=["none"],
                        help="torch.compile modes of the loss (training.compile_mode); none: eager")
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    config = yaml.safe_load(args.config.read_text())
    device = torch.device(args.device)
    image_size = args.image_size or config["demonstrations"]["image_size"]
    modes = [None if mode == "none" else mode for mode in args.compile_modes]
    rows = measure(config["training"], image_size, device, args.batches, args.precisions, args.steps, modes)
    record = {"device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu", "image_size": image_size,
              "torch": torch.__version__, "widths": config["training"]["policy"]["widths"], "variants": rows}
    args.out.write_text(json.dumps(record, indent=1) + "\n")


if __name__ == "__main__":
    main()
