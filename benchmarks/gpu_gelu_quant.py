"""The quantizing GELU activations of pi0.5 alone: the hand-written kernel (`models.pi05.fast.gelu_quant`)
against inductor's compiled composition and the unquantized activation, per call, side by side in one
process; with the kernel's equality to the hook path.

Shapes are pi0.5's at full size: the VLM's Gemma MLP at batch 1 (968 tokens x 16,384, bf16, GELU of
the gate times up), the action expert's (50 and 400 action tokens x 4,096, bf16) and the vision
tower's float32 GELU (768 and 6,144 patch rows x 4,304). Per shape: the fraction of elements equal
to `fake_quant_activation(F.gelu(gate, approximate="tanh") * up, bits)` computed eagerly (4 and 8
bits; must be 1.0), then microseconds per call (median of 20 replays of a CUDA graph of 20 calls) of
the unquantized op compiled by `static_sampling.inductor`, the op with int4 quantization compiled the
same way (what ran before the kernel), and the kernel at 4, 8, 16 and 32 warps and at its default.

    python benchmarks/gpu_gelu_quant.py --out benchmarks/results/gpu_gelu_quant.json
"""

from __future__ import annotations

import argparse
import json
import time

import torch
import torch.nn.functional as F  # noqa: N812

from vlaquantbench.models.pi05.fast import gelu_quant
from vlaquantbench.models.pi05.fast import static_sampling as pi05_static
from vlaquantbench.quant.grid import fake_quant_activation
from vlaquantbench.quant.hooks import quantizing_op

SHAPES = {"vlm_968x16384": (968, 16384, torch.bfloat16, True),
          "expert_50x4096": (50, 4096, torch.bfloat16, True),
          "expert_400x4096": (400, 4096, torch.bfloat16, True),
          "siglip_768x4304": (768, 4304, torch.float32, False),
          "siglip_b8_6144x4304": (6144, 4304, torch.float32, False)}


def graph_us(fn, args, calls: int = 20, reps: int = 20) -> float:
    """Median microseconds per call over `reps` replays of one CUDA graph of `calls` calls."""
    stream = torch.cuda.Stream()
    stream.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(stream):
        for _ in range(3):
            fn(*args)
    torch.cuda.current_stream().wait_stream(stream)
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph):
        for _ in range(calls):
            fn(*args)
    graph.replay()
    torch.cuda.synchronize()
    times = []
    for _ in range(reps):
        start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        start.record()
        graph.replay()
        end.record()
        torch.cuda.synchronize()
        times.append(start.elapsed_time(end) * 1e3 / calls)
    return sorted(times)[len(times) // 2]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    device = torch.device("cuda")
    g = torch.Generator(device="cpu").manual_seed(3)
    results = {}
    for name, (rows, cols, dtype, has_up) in SHAPES.items():
        gate = (torch.randn(rows, cols, generator=g) * 2).to(device, dtype)
        up = (torch.randn(rows, cols, generator=g) * 2).to(device, dtype) if has_up else None
        row = {}
        for bits in (4, 8):
            act = F.gelu(gate, approximate="tanh")
            reference = fake_quant_activation(act * up if has_up else act, bits)
            row[f"equal_a{bits}"] = (gelu_quant.gelu_fake_quant(gate, up, bits) == reference).double().mean().item()
        op = pi05_static.gelu_tanh_mul if has_up else pi05_static.gelu_tanh
        inputs = (gate, up) if has_up else (gate,)

        # The composition without the kernel (`compiler` None), compiled as the sampler compiles ops.
        row["compiled_quant4_us"] = graph_us(pi05_static.inductor(quantizing_op(op, 4, None)), inputs)
        row["plain_us"] = graph_us(pi05_static.inductor(op), inputs)
        for warps in (4, 8, 16, 32):
            row[f"kernel_w{warps}_us"] = graph_us(
                lambda *a, w=warps: gelu_quant.gelu_fake_quant(a[0], a[1] if has_up else None, 4, num_warps=w), inputs)
        row["kernel_default_us"] = graph_us(lambda *a: gelu_quant.gelu_fake_quant(a[0], a[1] if has_up else None, 4),
                                            inputs)
        print(name, json.dumps(row), flush=True)
        results[name] = row
    results["machine"] = {"gpu": torch.cuda.get_device_name(), "torch": torch.__version__,
                          "date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
    with open(args.out, "w") as f:
        json.dump(results, f, indent=1)


if __name__ == "__main__":
    main()
