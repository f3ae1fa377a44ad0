"""Fake-quant forward overhead on CPU: W4A4 (all 456 linear layers hooked) vs the same demo pi0.5.

Both policies come from one seeded `get_model_spec("pi05").build("demo")` in this process and are
timed alternately on identical inputs (one action chunk = prefix pass + 10 flow steps), so load
from other processes hits both alike. Prints and writes the median of the per-round time ratios.

    .venv/bin/python benchmarks/bench_fakequant_cpu.py [--rounds 7] [--threads 1] [--out benchmarks/results/fakequant_cpu.json]
"""

from __future__ import annotations

import argparse
import copy
import json
import platform
import statistics
import time
from pathlib import Path

import torch

from vlaquantbench.models import get_model_spec
from vlaquantbench.quant import QuantConfig, quantize_


def chunk_inputs(batch: int = 1, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    images = [torch.rand(batch, 3, 224, 224, generator=g) * 2 - 1 for _ in range(2)]
    image_masks = [torch.ones(batch, dtype=torch.bool) for _ in range(2)]
    tokens = torch.randint(0, 257152, (batch, 200), generator=g)
    token_masks = torch.ones(batch, 200, dtype=torch.bool)
    noise = torch.randn(batch, 50, 32, generator=g)
    return images, image_masks, tokens, token_masks, noise


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--preset", default="W4A4")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads (1: robust on a shared machine)")
    parser.add_argument("--out", default="benchmarks/results/fakequant_cpu.json")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    spec = get_model_spec("pi05")
    baseline = spec.build("demo", device="cpu", seed=0)
    quantized = copy.deepcopy(baseline)
    config = QuantConfig.from_preset(args.preset, scope="e2e")
    report = quantize_(quantized, config, config.select(quantized, spec.components))
    images, image_masks, tokens, token_masks, noise = chunk_inputs()

    def one_chunk(model) -> float:
        start = time.perf_counter()
        model.sample_actions(images, image_masks, tokens, token_masks, noise=noise)
        return time.perf_counter() - start

    one_chunk(baseline), one_chunk(quantized)  # warm-up: allocator and kernel selection
    times = {"baseline": [], "quantized": []}
    for _ in range(args.rounds):
        times["baseline"].append(one_chunk(baseline))
        times["quantized"].append(one_chunk(quantized))
    medians = {k: statistics.median(v) for k, v in times.items()}
    # Each round times both policies back to back, so its ratio cancels load that drifts between rounds.
    round_ratios = [q / b for q, b in zip(times["quantized"], times["baseline"])]
    ratio = statistics.median(round_ratios)
    result = {
        "benchmark": "fake-quant forward overhead, demo pi05 (reduced-width real lerobot PI05Pytorch), CPU",
        "preset": args.preset,
        "scope": "e2e",
        "quantized_layers": sum(c["layers"] for c in report.components.values()),
        "hooks_fired": report.to_header()["hooks"]["fired"],
        "unit": "seconds per action chunk (prefix pass + 10 flow steps), batch 1, 224 px, 2 cameras",
        "rounds": args.rounds,
        "times_s": times,
        "median_s": medians,
        "round_ratios": round_ratios,
        "overhead_ratio": ratio,
        "overhead_ratio_definition": "median over rounds of quantized/baseline time within the round",
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "cpu": platform.processor() or platform.machine(),
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"{args.preset} fake-quant / baseline chunk time: median paired ratio {ratio:.2f}x over {args.rounds} "
          f"alternating rounds (medians {medians['quantized']:.3f}s / {medians['baseline']:.3f}s) -> {out}")


if __name__ == "__main__":
    main()
