"""Training step rate of the trained pi0.5 (config/trained_study.yaml's `training`) by precision, batch size and
how the step runs (eager, captured as a CUDA graph, compiled), on `vlaquantbench.training.TrainingStep`.

    python benchmarks/gpu_train_step.py --out FILE.json [--config config/trained_study.yaml] [--device cuda]
        [--batches 128 256] [--precisions float32 bfloat16] [--graphs off on] [--compile-modes none default]
        [--check-graph-steps 8] [--steps 30]

`--check-graph-steps N` first compares N captured steps with N eager ones from one initialization on the same
inputs (`graph_check`: losses and weights). The frames: a small LeRobotDataset of random images at the
demonstrations' size (the step costs the same whatever the pixels). Writes `--out` (steps and samples a second,
peak memory, the first 5 steps' seconds: capture or compile), which benchmarks/gpu_train_policy.sh sizes from.
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

from vlaquantbench.training import TrainingConfig


def tiny_dataset(root: Path, image_size: int, tasks: list[str], frames: int = 40):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    vector = {"dtype": "float32", "shape": (4,), "names": None}
    features = {"observation.image": {"dtype": "image", "shape": (image_size, image_size, 3), "names": ["height", "width", "channel"]},
                "observation.state": vector, "action": vector}
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


def _build(training: TrainingConfig, dataset, tokenizer, device: torch.device, compile_mode: str | None = None):
    from vlaquantbench.models.pi05 import trained
    from vlaquantbench.training.frames import DeviceFrames
    from vlaquantbench.training.loop import compile_policy

    torch.manual_seed(0)
    policy, preprocessor, _, _ = trained.build_policy(dataset.meta, training.policy, training.tokenizer_repo,
                                                      tokenizer, str(device))
    compile_policy(policy, compile_mode)
    frames = DeviceFrames(dataset, preprocessor, policy.config.chunk_size, device)
    optimizer = policy.config.get_optimizer_preset().build(policy.get_optim_params())
    scheduler = policy.config.get_scheduler_preset().build(optimizer, 10_000)
    policy.train()
    return policy, frames, optimizer, scheduler, policy.config.get_optimizer_preset().grad_clip_norm


def measure(training: TrainingConfig, dataset, tokenizer, device: torch.device, batches: list[int], precisions: list[str],
            steps: int, compile_modes: list[str | None] = (None,), graphs: list[bool] = (False,)) -> list[dict]:
    from vlaquantbench.training.loop import TrainingStep

    results = []
    variants = [(mode, graph, precision, batch) for mode in compile_modes for graph in graphs
                for precision in precisions for batch in batches if not (mode and graph)]
    for compile_mode, graph, precision, batch_size in variants:
        policy, frames, optimizer, scheduler, clip = _build(training, dataset, tokenizer, device, compile_mode)
        autocast = {"float32": None, "bfloat16": torch.bfloat16}[precision]
        step = TrainingStep(policy, optimizer, scheduler, clip, autocast, cuda_graph=graph)
        shift = training.random_shift_px

        def one_step():
            return step(frames.batch(torch.randint(0, len(frames), (batch_size,), device=device), shift))

        warming = time.perf_counter()
        torch.stack([one_step() for _ in range(5)]).sum().item()
        warmup_s = time.perf_counter() - warming
        if device.type == "cuda":
            torch.cuda.synchronize(device)
            torch.cuda.reset_peak_memory_stats(device)
        began = time.perf_counter()
        losses = [one_step() for _ in range(steps)]
        torch.stack(losses).sum().item()  # waits for the device
        seconds = time.perf_counter() - began
        row = {"compile_mode": compile_mode, "cuda_graph": graph, "precision": precision, "batch_size": batch_size,
               "steps": steps, "first_5_steps_s": round(warmup_s, 1),
               "steps_per_s": round(steps / seconds, 2), "samples_per_s": round(steps * batch_size / seconds),
               "peak_gib": round(torch.cuda.max_memory_allocated(device) / 2**30, 2) if device.type == "cuda" else None}
        print(json.dumps(row), flush=True)
        results.append(row)
        del policy, optimizer, frames, step
    return results


def graph_check(training: TrainingConfig, dataset, tokenizer, device: torch.device, batch_size: int, steps: int) -> dict:
    """The captured step against the eager one: two policies from one initialization take `steps` steps on the
    same batches, noise and time (drawn once, before either runs); their losses and final weights, compared."""
    from vlaquantbench.training.loop import TrainingStep, _flow_sample

    runs, inputs = [], []
    for graph in (False, True):
        policy, frames, optimizer, scheduler, clip = _build(training, dataset, tokenizer, device)
        initial = torch.cat([p.detach().flatten() for p in policy.parameters()])
        if not inputs:
            torch.manual_seed(1)
            for _ in range(steps):
                batch = frames.batch(torch.randint(0, len(frames), (batch_size,), device=device),
                                     training.random_shift_px)
                inputs.append((batch, *_flow_sample(policy, batch)))
        step = TrainingStep(policy, optimizer, scheduler, clip, None, cuda_graph=graph)
        losses = torch.stack([step(*item) for item in inputs]).tolist()
        final = torch.cat([p.detach().flatten() for p in policy.parameters()])
        runs.append((losses, final, (final - initial).abs().max().item()))
        del policy, optimizer, frames, step
    (eager_losses, eager_weights, moved), (graph_losses, graph_weights, _) = runs
    check = {"batch_size": batch_size, "steps": steps, "eager_losses": eager_losses, "graph_losses": graph_losses,
             "max_rel_loss_diff": max(abs(a - b) / abs(a) for a, b in zip(eager_losses, graph_losses)),
             "max_abs_weight_diff": (eager_weights - graph_weights).abs().max().item(),
             "max_abs_weight_change_eager": moved}
    print(json.dumps(check), flush=True)
    return check


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", type=Path, default=Path("config/trained_study.yaml"))
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--image-size", type=int, default=None, help="default: the config's demonstrations.image_size")
    parser.add_argument("--batches", type=int, nargs="+", default=[128, 256])
    parser.add_argument("--precisions", nargs="+", default=["float32", "bfloat16"], choices=["float32", "bfloat16"])
    parser.add_argument("--compile-modes", nargs="+", default=["none"],
                        help="torch.compile modes of the loss (training.compile_mode); none: eager")
    parser.add_argument("--graphs", nargs="+", default=["off"], choices=["off", "on"],
                        help="the step's loss and gradients captured as a CUDA graph (training.cuda_graph)")
    parser.add_argument("--check-graph-steps", type=int, default=0,
                        help="first compare this many captured steps with eager ones (0: no check)")
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from vlaquantbench.models.pi05 import task_tokenizer

    config = yaml.safe_load(args.config.read_text())
    training = TrainingConfig.from_dict(config["training"], str(args.config))
    device = torch.device(args.device)
    image_size = args.image_size or config["demonstrations"]["image_size"]
    modes = [None if mode == "none" else mode for mode in args.compile_modes]
    torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = True
    tasks = ["Press a button from the top", "Push and close a drawer"]
    record = {"device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu", "image_size": image_size,
              "torch": torch.__version__, "widths": training.policy["widths"]}
    with tempfile.TemporaryDirectory() as tmp:
        tiny_dataset(Path(tmp) / "data", image_size, tasks)
        dataset = LeRobotDataset("vlaquantbench/step-rate", root=Path(tmp) / "data")
        tokenizer = task_tokenizer.build_task_tokenizer(tasks)
        if args.check_graph_steps:
            record["graph_check"] = graph_check(training, dataset, tokenizer, device, min(args.batches),
                                                args.check_graph_steps)
            args.out.write_text(json.dumps(record, indent=1) + "\n")
        record["variants"] = measure(training, dataset, tokenizer, device, args.batches, args.precisions,
                                     args.steps, modes, [graph == "on" for graph in args.graphs])
    args.out.write_text(json.dumps(record, indent=1) + "\n")


if __name__ == "__main__":
    main()
