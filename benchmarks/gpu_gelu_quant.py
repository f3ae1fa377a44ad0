"""The quantizing GELU activations of pi0.5 alone: the hand-written kernel (`models.pi05.fast.gelu_quant`)
in its two forms against the unquantized activation, per call, side by side in one
process; with the kernel's equality to the hook path.

Shapes are pi0.5's at full size with LIBERO's two cameras: the VLM's Gemma MLP (712 prefix tokens
per observation x 16,384, bf16, GELU of the gate times up; 968 with three cameras), the action
expert's (50 action tokens per observation x 4,096, bf16) and the vision tower's float32 GELU (256
patch rows per image x 4,304), at batch 1, 8 and 32 where they differ in kind. Per shape: the fraction
of elements equal to `fake_quant_activation(F.gelu(gate, approximate="tanh") * up, bits)` computed
eagerly (4 and 8 bits for the kernel's own launch choice, 4 bits for every other launch; must be
1.0), then microseconds per call (median of 20 replays of a CUDA graph of 20 calls) of the
unquantized op compiled by `static_sampling.inductor` (the floor), the kernel with each row held whole (32 warps
up to two rows per multiprocessor, else 16 values per thread; 8 and 16 warps for rows of up to 4,096),
the chunked kernel at several chunk sizes and warps, and the kernel's own choice (`gelu_quant._launch`).

    python benchmarks/gpu_gelu_quant.py --out benchmarks/results/gpu_gelu_quant.json
"""

from __future__ import annotations

import argparse
import json
import time

import torch
import torch.nn.functional as F  # noqa: N812
import triton

from vlaquantbench.models.pi05.fast import gelu_quant
from vlaquantbench.models.pi05.fast import static_sampling as pi05_static
from vlaquantbench.quant.grid import fake_quant_activation

SHAPES = {"vlm_712x16384": (712, 16384, torch.bfloat16, True),
          "vlm_968x16384": (968, 16384, torch.bfloat16, True),
          "vlm_b8_5696x16384": (5696, 16384, torch.bfloat16, True),
          "expert_50x4096": (50, 4096, torch.bfloat16, True),
          "expert_400x4096": (400, 4096, torch.bfloat16, True),
          "expert_1600x4096": (1600, 4096, torch.bfloat16, True),
          "siglip_512x4304": (512, 4304, torch.float32, False),
          "siglip_b8_4096x4304": (4096, 4304, torch.float32, False)}
CHUNKED = [(2048, 4), (2048, 8), (2048, 16), (1024, 8), (4096, 8)]


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
        act = F.gelu(gate, approximate="tanh")
        references = {bits: fake_quant_activation(act * up if has_up else act, bits) for bits in (4, 8)}
        whole_warps = 32 if rows <= 2 * torch.cuda.get_device_properties(device).multi_processor_count else \
            min(32, max(4, triton.next_power_of_2(cols) // 512))
        launches = {"chosen": {}, f"whole_row_w{whole_warps}": {"chunk": 0, "num_warps": whole_warps}}
        launches |= {f"whole_row_w{w}": {"chunk": 0, "num_warps": w} for w in (8, 16) if cols <= 4096}
        launches |= {f"chunk{c}_w{w}": {"chunk": c, "num_warps": w} for c, w in CHUNKED}
        for key, launch in launches.items():
            for bits in (4, 8) if key == "chosen" else (4,):
                got = gelu_quant.gelu_fake_quant(gate, up, bits, **launch)
                row[f"equal_a{bits}_{key}"] = (got == references[bits]).double().mean().item()
        op = pi05_static.gelu_tanh_mul if has_up else pi05_static.gelu_tanh
        inputs = (gate, up) if has_up else (gate,)

        row["plain_us"] = graph_us(pi05_static.inductor(op), inputs)
        for key, launch in launches.items():
            row[f"kernel_{key}_us"] = graph_us(
                lambda *a, launch=launch: gelu_quant.gelu_fake_quant(a[0], a[1] if has_up else None, 4, **launch), inputs)
        row["chosen_launch"] = gelu_quant._launch(rows, cols, device)
        row["chosen_vs_plain"] = row["kernel_chosen_us"] / row["plain_us"]
        row["chosen_vs_whole_row"] = row["kernel_chosen_us"] / row[f"kernel_whole_row_w{whole_warps}_us"]
        print(name, json.dumps(row), flush=True)
        results[name] = row
    results["machine"] = {"gpu": torch.cuda.get_device_name(), "torch": torch.__version__,
                          "date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
    with open(args.out, "w") as f:
        json.dump(results, f, indent=1)


if __name__ == "__main__":
    main()
