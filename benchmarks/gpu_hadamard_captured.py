"""pi0.5 W4A4 with Hadamard rotations inside the captured chunk: chunk time of
BASELINE, plain W4A4 fake quantization and W4A4 + Hadamard, side by side in one process, at batch
1, 8 and 32 with 2 cameras.

Cells (all captured, `CapturedSampler`; lerobot 0.6.1 `PI05Pytorch` at full size, random weights
seed 0, 2 cameras at 224 px, 200 prompt tokens, 10 flow steps; scope e2e, all 456 linears):
    baseline        BASELINE (bf16, the SigLIP tower and projector float32)
    w4a4            rtn-W4A4-e2e: the fused per-token quantization of every linear's input
    w4a4_hadamard   hadamard-W4A4-e2e: every linear's input rotated by its block-Hadamard transform
                    (`quant.hadamard.BlockHadamard`) and quantized per token by one Triton kernel
                    after the op that produces it (`quant.fused_kernel.rotated_fake_quant`: products
                    with the +-1 Hadamard factors on the tensor cores); once per input that q/k/v or
                    gate/up share (`quant.hooks.Rotated`)
Also recorded: the linear groups the captured sampler fused, every hook's count after capture, the
actions of each cell against BASELINE, and the Hadamard cell's captured chunk against lerobot's eager
`sample_actions` of the same quantized model (batch 1; `models.adapter.CUDA_PROBE_BOUND` is 0.05).
Timing: `gpu_policy_inference.alternate` (the cells take turns `--rounds` times, each turn capturing
again), median of the repeats: the typical chunk, not the best.

    python benchmarks/gpu_hadamard_captured.py --out benchmarks/results/gpu_hadamard_captured.json   # ~6 min, H200
    python benchmarks/gpu_hadamard_captured.py --device cpu --smoke --out /tmp/h.json   # demo widths, CPU, inductor
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from gpu_fp8_real import build, groups_summary, rel_l2  # noqa: E402
from gpu_policy_inference import alternate, chunk_inputs, machine  # noqa: E402

from vlaquantbench.models import get_model_spec  # noqa: E402
from vlaquantbench.models.pi05.fast import CapturedSampler  # noqa: E402
from vlaquantbench.quant.hooks import Rotated  # noqa: E402

CELLS = {"baseline": ("BASELINE", "rtn"), "w4a4": ("W4A4", "rtn"), "w4a4_hadamard": ("W4A4", "hadamard")}


def rotated_groups(sampler: CapturedSampler) -> int:
    groups = sampler._model_groups()
    return sum(isinstance(g.input_quantization, Rotated)
               for layer in groups.vision + groups.prefix + groups.expert
               for g in (layer.qkv, layer.out, layer.mlp_in, layer.mlp_out))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", required=True)
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 8, 32])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--cameras", type=int, default=2)
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--smoke", action="store_true",
                        help="demo widths, batches 1 and 2, 2 flow steps, 2 repeats, 1 round (checks the script runs)")
    args = parser.parse_args()
    variant = "full"
    if args.smoke:
        variant, args.batches, args.steps, args.repeats, args.rounds = "demo", [1, 2], 2, 2, 1
    device = torch.device(args.device)
    started = time.perf_counter()
    results = {"machine": machine() if device.type == "cuda" else {"device": "cpu"}, "variant": variant,
               "cameras": args.cameras, "steps": args.steps, "batches": args.batches}
    write = lambda: Path(args.out).write_text(json.dumps(results, indent=1))  # noqa: E731

    spec = get_model_spec("pi05")
    inputs = {b: chunk_inputs(b, device, seed=b, cameras=args.cameras) for b in args.batches}
    samplers, cells, reports = {}, {}, {}
    for name, (preset, method) in CELLS.items():
        t0 = time.perf_counter()
        model, report = build(spec, device, preset, method, variant)
        # graph per timed batch; on the CPU the captured code runs eagerly with its ops compiled
        sampler = CapturedSampler(model, num_steps=args.steps, graph_sizes=args.batches, fuse_elementwise=True)
        cells[name] = {"preset": preset, "method": method, "format": report.result.format,
                       "build_s": time.perf_counter() - t0, "linear_groups": groups_summary(sampler),
                       "rotated_groups": rotated_groups(sampler), "quantized_layers": len(report.result.hooks)}
        samplers[name], reports[name] = sampler, report
        print(name, cells[name], flush=True)
    results["cells"] = cells
    write()  # after every stage: a run cut short by its time limit keeps what it measured

    # Actions on the same inputs; the Hadamard cell's captured chunk against lerobot's eager one.
    actions = {}
    for name, sampler in samplers.items():
        for other in samplers.values():
            other.reset()
        actions[name] = {b: sampler(*inputs[b]).float() for b in args.batches}
        cells[name]["unfired_after_capture"] = reports[name].unfired()
    results["actions_rel_l2_vs_baseline"] = {
        name: {b: rel_l2(actions[name][b], actions["baseline"][b]) for b in args.batches} for name in CELLS if name != "baseline"}
    images, img_masks, tokens, masks, noise = inputs[args.batches[0]]
    with torch.no_grad():
        eager = samplers["w4a4_hadamard"].model.sample_actions(images, img_masks, tokens, masks, noise=noise.clone(),
                                                               num_steps=args.steps)
    results["hadamard_captured_vs_eager_rel_l2"] = {args.batches[0]: rel_l2(actions["w4a4_hadamard"][args.batches[0]], eager)}
    print("actions rel L2 vs baseline:", results["actions_rel_l2_vs_baseline"],
          "\nhadamard captured vs eager:", results["hadamard_captured_vs_eager_rel_l2"], flush=True)
    write()

    ms = alternate(samplers, inputs, args.batches, args.repeats, args.rounds)
    results["chunk_ms"] = ms
    results["vs_baseline"] = {n: {b: ms[n][b] / ms["baseline"][b] for b in args.batches} for n in CELLS if n != "baseline"}
    results["hadamard_vs_w4a4"] = {b: ms["w4a4_hadamard"][b] / ms["w4a4"][b] for b in args.batches}
    results["rounds"], results["repeats_per_round"] = args.rounds, args.repeats
    results["wall_s"] = time.perf_counter() - started
    print("chunk ms:", ms, "\nvs baseline:", results["vs_baseline"], flush=True)
    write()

    print("wrote", args.out)


if __name__ == "__main__":
    main()
