"""Should the pi0.5 fork stay? lerobot's own `sample_actions` under `torch.compile(mode="reduce-overhead")`
against the captured sampler (`vlaquantbench.models.pi05.fast`), side by side in one process, with
the same counting activation hooks installed by `quantize_`.

Per preset (BASELINE, W4A4 end to end) and batch size (1, 8, 32): median chunk latency of eager
lerobot, compiled lerobot and the captured fork; first-call (compile/capture) time; each path's
chunk against eager lerobot's on the same input (relative L2, max abs); and the hook counts: a
compiled chunk must advance every layer's quantizer exactly as an eager chunk does (dynamo replays
the counter increments after each graph), the captured fork must have run every quantizer at
capture (a replay runs no Python).

Decision rule (issue 14): keep whichever is simpler at equal speed. Compiled lerobot is the simpler
(no re-implementation of `sample_actions`); it wins when, at every batch size and preset, its
median is within 5% of the captured fork's (`compiled_over_captured` <= 1.05), its hook counts
match eager's and its chunk is within the fast-path probe's CUDA bound (`models.adapter.CUDA_PROBE_BOUND`;
the CPU smoke run uses it too).
The script prints and records the verdict; the GPU measurement decides.

Model: `PI05Pytorch` at full size with random weights (bf16, lerobot's layout) on CUDA; on the CPU
the demo build (`--device cpu`: a quick smoke of the script, not a speed claim; `--backend eager`
there traces with dynamo without inductor's CPU compile).

    python benchmarks/gpu_compile_vs_captured.py --out benchmarks/results/gpu_compile_vs_captured.json
    python benchmarks/gpu_compile_vs_captured.py --device cpu --backend eager --batches 1 --flow-steps 1 \\
        --repeats 1 --out benchmarks/results/compile_vs_captured_cpu_smoke.json
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time

import torch
from gpu_policy_inference import chunk_inputs, released_weights, requantize

from vlaquantbench.models import get_model_spec
from vlaquantbench.models.adapter import CUDA_PROBE_BOUND
from vlaquantbench.models.pi05.fast import CapturedSampler
from vlaquantbench.quant.fused_kernel import fuse_activation_hooks

EQUAL_SPEED = 1.05  # compiled may be this much slower than captured and still count as "equal speed"


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize()


def timed(fn, device, warmup: int, repeats: int) -> tuple[float, float]:
    """(seconds of the first call, median seconds of `repeats` calls after `warmup` more)."""
    _sync(device)
    start = time.perf_counter()
    fn()
    _sync(device)
    first = time.perf_counter() - start
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        _sync(device)
        start = time.perf_counter()
        fn()
        _sync(device)
        times.append(time.perf_counter() - start)
    return first, statistics.median(times)


def closeness(actions: torch.Tensor, eager: torch.Tensor) -> dict:
    a, e = actions.double(), eager.double()
    return {"rel_l2": ((a - e).norm() / e.norm()).item(), "max_abs_diff": (a - e).abs().max().item()}


def compiled_sampler(model, steps: int, backend: str):
    # One compilation per batch size, as the captured fork captures one graph per batch size.
    fn = lambda *inputs: model.sample_actions(*inputs[:4], noise=inputs[4].clone(), num_steps=steps)  # noqa: E731
    if backend == "inductor":
        return torch.compile(fn, mode="reduce-overhead", dynamic=False)
    return torch.compile(fn, backend=backend, dynamic=False)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", required=True)
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--backend", default="inductor", help="torch.compile backend (inductor: mode reduce-overhead)")
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 8, 32])
    parser.add_argument("--presets", nargs="+", default=["BASELINE", "W4A4"])
    parser.add_argument("--flow-steps", type=int, default=10)
    parser.add_argument("--repeats", type=int, default=10)
    args = parser.parse_args()

    started = time.perf_counter()
    device = torch.device(args.device)
    spec = get_model_spec("pi05")
    model = spec.build(variant="full" if device.type == "cuda" else "demo", device=device, seed=0).eval()
    torch._dynamo.config.recompile_limit = max(torch._dynamo.config.recompile_limit, 64)
    inputs = {b: chunk_inputs(b, device) for b in args.batches}
    originals = released_weights(model, spec)
    (metric, bound), = CUDA_PROBE_BOUND.items()
    results = {"device": torch.cuda.get_device_name() if device.type == "cuda" else platform.processor() or "cpu",
               "torch": torch.__version__, "backend": args.backend, "flow_steps": args.flow_steps,
               "probe_bound": {metric: bound}, "cells": []}

    for preset in args.presets:
        report = requantize(model, spec, originals, preset)
        cell = {"preset": preset, "hooks": len(report.result.hooks), "batches": {}}
        compiled = compiled_sampler(model, args.flow_steps, args.backend)
        eager_chunks = {}
        with torch.no_grad():
            for b in args.batches:
                row = cell["batches"].setdefault(b, {})
                report.reset_hook_calls()
                eager_chunks[b] = model.sample_actions(*inputs[b][:4], noise=inputs[b][4].clone(), num_steps=args.flow_steps)
                per_chunk = report.hook_calls()
                _, row["eager_ms"] = timed(lambda b=b: model.sample_actions(*inputs[b][:4], noise=inputs[b][4].clone(),
                                                                           num_steps=args.flow_steps),
                                           device, warmup=1, repeats=args.repeats)
                # Printed before the first compiled call: a run stopped at its time limit shows how long
                # the compile had been running.
                print(f"[{preset}] b{b}: eager {1e3 * row['eager_ms']:.1f} ms; compiling lerobot's sample_actions "
                      f"at {time.perf_counter() - started:.0f} s into the run", flush=True)
                first, row["compiled_ms"] = timed(lambda b=b: compiled(*inputs[b]), device, warmup=2, repeats=args.repeats)
                row["compiled_first_call_s"] = first
                report.reset_hook_calls()
                chunk = compiled(*inputs[b])
                row["compiled_hook_counts_match_eager"] = report.hook_calls() == per_chunk
                row["compiled_vs_eager"] = closeness(chunk, eager_chunks[b])
                print(f"[{preset}] b{b}: eager {1e3 * row['eager_ms']:.1f} ms, compiled {1e3 * row['compiled_ms']:.2f} ms "
                      f"(first {first:.1f} s), counts match {row['compiled_hook_counts_match_eager']}, "
                      f"{row['compiled_vs_eager']}", flush=True)

            # The captured fork as the runner sets it up: fused Triton hook transforms on CUDA.
            cell["fused_hooks"] = fuse_activation_hooks(report) if device.type == "cuda" else 0
            sampler = CapturedSampler(model, num_steps=args.flow_steps, graph_sizes=args.batches)  # one graph per batch
            for b in args.batches:
                row = cell["batches"][b]
                report.reset_hook_calls()
                first, row["captured_ms"] = timed(lambda b=b: sampler(*inputs[b]), device, warmup=2, repeats=args.repeats)
                row["captured_first_call_s"] = first
                row["captured_unfired_after_capture"] = report.unfired()
                row["captured_vs_eager"] = closeness(sampler(*inputs[b]), eager_chunks[b])
                row["compiled_over_captured"] = row["compiled_ms"] / row["captured_ms"]
                print(f"[{preset}] b{b}: captured {1e3 * row['captured_ms']:.2f} ms (first {first:.1f} s), "
                      f"compiled/captured {row['compiled_over_captured']:.2f}, {row['captured_vs_eager']}", flush=True)
        report.remove_hooks()
        del compiled, sampler
        torch._dynamo.reset()
        results["cells"].append(cell)

    rows = [row for cell in results["cells"] for row in cell["batches"].values()]
    compiled_ok = all(r["compiled_hook_counts_match_eager"] and r["compiled_vs_eager"][metric] <= bound for r in rows)
    equal_speed = all(r["compiled_over_captured"] <= EQUAL_SPEED for r in rows)
    results["verdict"] = {
        "compiled_hooks_and_closeness_ok": compiled_ok,
        "captured_hooks_and_closeness_ok": all(not r["captured_unfired_after_capture"]
                                               and r["captured_vs_eager"][metric] <= bound for r in rows),
        "compiled_within_equal_speed": equal_speed,
        "rule": f"keep compiled lerobot if its hooks and closeness pass and compiled/captured <= {EQUAL_SPEED} "
                "everywhere; else keep the captured fork",
        "keep": "compiled lerobot sample_actions" if compiled_ok and equal_speed else "captured fork",
        "speed_claim": device.type == "cuda",
    }
    print(json.dumps(results["verdict"], indent=1))
    with open(args.out, "w") as f:
        json.dump(results, f, indent=1)


if __name__ == "__main__":
    main()
