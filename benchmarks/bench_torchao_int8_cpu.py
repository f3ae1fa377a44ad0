"""W8A8 int8 dynamic linear on the CPU: torchao's `Int8DynamicActivationInt8WeightConfig` next to the
hand-written `quant.kernels.Int8DynamicLinear` (per-token int8 inputs, per-channel int8 weights,
`torch._int_mm`), timed alternately in one process on identical inputs so that load from other
processes hits both alike; also their outputs' relative difference and each one's error against
the float product. Prints and writes the median per-round time ratio (torchao / hand-written).

    .venv/bin/python benchmarks/bench_torchao_int8_cpu.py [--rounds 9] [--threads 1] \
        [--out benchmarks/results/torchao_int8_cpu.json]
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
import torchao
from torchao.quantization import Int8DynamicActivationInt8WeightConfig
from torchao.quantization import quantize_ as ao_quantize

from vlaquantbench.quant.kernels.int8 import Int8DynamicLinear

# (tokens, in, out): OpenVLA-OFT-like LLM projections at one chunk, and the demo pi0.5 expert's
SHAPES = [(64, 4096, 4096), (64, 4096, 11008), (50, 256, 1024)]


def per_call_s(fn, calls: int) -> float:
    start = time.perf_counter()
    for _ in range(calls):
        fn()
    return (time.perf_counter() - start) / calls


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=9)
    parser.add_argument("--calls", type=int, default=5)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", default="benchmarks/results/torchao_int8_cpu.json")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    results = []
    with torch.no_grad():
        for tokens, fan_in, fan_out in SHAPES:
            linear = torch.nn.Linear(fan_in, fan_out)
            x = torch.randn(1, tokens, fan_in)
            hand = Int8DynamicLinear(linear)
            ao = torch.nn.Sequential(copy.deepcopy(linear))
            ao_quantize(ao, Int8DynamicActivationInt8WeightConfig())
            ref = linear(x)
            y_hand, y_ao = hand(x), ao(x)
            ratios, t_hand, t_ao = [], [], []
            for _ in range(args.rounds):
                a = per_call_s(lambda: hand(x), args.calls)
                b = per_call_s(lambda: ao(x), args.calls)
                t_hand.append(a)
                t_ao.append(b)
                ratios.append(b / a)
            row = {
                "shape": [tokens, fan_in, fan_out],
                "hand_ms": 1e3 * statistics.median(t_hand),
                "torchao_ms": 1e3 * statistics.median(t_ao),
                "torchao_over_hand": statistics.median(ratios),
                "rel_diff_torchao_vs_hand": ((y_ao - y_hand).norm() / y_hand.norm()).item(),
                "rel_err_hand": ((y_hand - ref).norm() / ref.norm()).item(),
                "rel_err_torchao": ((y_ao - ref).norm() / ref.norm()).item(),
            }
            results.append(row)
            print(json.dumps(row), flush=True)
    out = {"date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "torch": torch.__version__,
           "torchao": torchao.__version__, "python": platform.python_version(), "threads": args.threads,
           "rounds": args.rounds, "calls": args.calls, "results": results}
    Path(args.out).write_text(json.dumps(out, indent=2) + "\n")


if __name__ == "__main__":
    main()
