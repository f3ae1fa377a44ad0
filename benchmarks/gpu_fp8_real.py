"""pi0.5 with real FP8, INT8 and INT4 kernels against BF16 and fake quantization, side by side in one
process: captured chunk time at batch 1, 8 and 32 with 2 cameras, weight memory, and the
actions' relative L2 of each form against the others on the same inputs.

Cells (all captured, `CapturedSampler`; lerobot 0.6.1 `PI05Pytorch` at full size, random weights
seed 0, 2 cameras at 224 px, 200 prompt tokens, 10 flow steps; scope e2e, all 456 linears):
    bf16       BASELINE (released precision: bf16, the SigLIP tower and projector float32)
    fakequant  rtn-FP8E4M3-e2e: e4m3 per-channel weights and per-token inputs, values rounded and
               the products in bf16/float32 (the fused hooks, producer-fused quantization)
    fp8real    fp8-W8A8-e2e: e4m3 weights stored as FP8 (`quant.kernels.fp8.Fp8DynamicLinear`),
               per-token input casts computed by the producing op, `torch._scaled_mm` row-wise (products
               of at most 64 rows: `quant.kernels.scaled_gemm`)
    int8real   int8_dynamic-W8A8-e2e: int8 weights (`quant.kernels.int8.Int8DynamicLinear`), per-token int8
               input casts computed by the producing op, `quant.kernels.scaled_gemm` (int32 sums, the float32
               rescale in its epilogue)
    int4       int4wo-W4-e2e: int4 weights in asymmetric groups of 128, bf16 activations, the Triton W4A16
               GEMM of `quant.kernels.scaled_gemm`; its layers run one by one (nothing to cast)
Not timed, for the actions only (batch 1): fakequant_int8 (rtn-W8A8-e2e, the fake-quantized
counterpart of int8real).
Timing: `gpu_policy_inference.alternate` (the cells take turns `--rounds` times, each turn
capturing again), median of the repeats: the typical chunk, not the best.

    python benchmarks/gpu_fp8_real.py --out benchmarks/results/gpu_fp8_real.json      # ~6 min on an H200
It keeps every cell's model resident (about 57 GiB): batch 32 runs out of memory on an 80 GB card. For one model
at a time beside BF16, on any card: `gpu_kernel_shapes.py` (its `profile` step).
    python benchmarks/gpu_fp8_real.py --checks-only --out /tmp/checks.json            # ~1 min
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from gpu_policy_inference import alternate, chunk_inputs, machine  # noqa: E402

from vlaquantbench.models import get_model_spec  # noqa: E402
from vlaquantbench.models.pi05.fast import CapturedSampler  # noqa: E402
from vlaquantbench.models.pi05.fast import static_sampling  # noqa: E402
from vlaquantbench.models.pi05.fast.linear_groups import LinearGroup  # noqa: E402
from vlaquantbench.quant import QuantConfig, quantize_  # noqa: E402
from vlaquantbench.quant.fused_kernel import fuse_activation_hooks  # noqa: E402
from vlaquantbench.quant.grid import PerTokenCast  # noqa: E402
from vlaquantbench.quant.hooks import CountingHook  # noqa: E402
from vlaquantbench.quant.input_transform import InputTransform  # noqa: E402
from vlaquantbench.quant.kernels.fp8 import Fp8DynamicLinear  # noqa: E402
from vlaquantbench.quant.kernels.int8 import Int8DynamicLinear  # noqa: E402
from vlaquantbench.quant.kernels.packed import FP8  # noqa: E402

CELLS = {"bf16": ("BASELINE", "rtn"), "fakequant": ("FP8E4M3", "rtn"), "fp8real": ("W8A8", "fp8"),
         "int8real": ("W8A8", "int8_dynamic"), "int4": ("W4", "int4wo")}
REFERENCE_CELLS = {"fakequant_int8": ("W8A8", "rtn")}
REAL_CELLS = ("fp8real", "int8real", "int4")
# (form, its fake-quantized counterpart or BF16) whose actions are compared
ACTION_PAIRS = (("fp8real", "fakequant"), ("fp8real", "bf16"), ("fakequant", "bf16"), ("int8real", "fakequant_int8"),
                ("int8real", "bf16"), ("fakequant_int8", "bf16"), ("int4", "bf16"))
STEPS = 10
GiB = 2**30


def rel_l2(a: torch.Tensor, b: torch.Tensor) -> float:
    return ((a.float() - b.float()).norm() / b.float().norm()).item()


def kernel_checks(device) -> dict:
    """The real W8A8 pieces (FP8 and INT8) on this GPU against references on fresh random inputs: the
    producer-fused cast (compiled with an RMSNorm and with a float32 LayerNorm) against `PerTokenCast`
    run eagerly, and a merged group's product against its members called as modules and against float64."""
    return {**_kernel_checks(device, Fp8DynamicLinear, FP8, ""),
            **_kernel_checks(device, Int8DynamicLinear, torch.int8, "int8_")}


def _kernel_checks(device, layer_class, dtype, prefix: str) -> dict:
    out = {}
    g = torch.Generator(device="cpu").manual_seed(1)
    for name, (op, args) in {
        "rms_norm_bf16": (static_sampling.rms_norm, (torch.randn(2, 968, 2048, generator=g).to(device, torch.bfloat16),
                                                    torch.randn(2048, generator=g).to(device), 1e-6)),
        "layer_norm_f32": (static_sampling.layer_norm, (torch.randn(4, 256, 1152, generator=g).to(device),
                                                        torch.randn(1152, generator=g).to(device),
                                                        torch.randn(1152, generator=g).to(device), 1e-6)),
    }.items():
        layers = [layer_class(torch.nn.Linear(args[0].shape[-1], 256, device=device, dtype=args[0].dtype))
                  for _ in range(3)]
        for layer in layers:
            CountingHook(layer, InputTransform())
        group = LinearGroup(layers)
        rows = group.input_from(op, args, static_sampling.inductor)
        reference = PerTokenCast(dtype)(op(*args))
        fused = group(rows)
        modules = [layer(op(*args)) for layer in layers]
        x64 = (reference.values.double() * reference.scales.double())
        exact = [x64 @ (getattr(layer, layer.WEIGHT).double() * layer.weight_scale.double().t()).t() + layer.bias.double()
                 for layer in layers]
        out[prefix + name] = {
            "cast_values_equal_fraction": (rows.values.view(torch.uint8) == reference.values.view(torch.uint8)).float().mean().item(),
            "cast_scales_max_rel_diff": ((rows.scales - reference.scales).abs() / reference.scales).max().item(),
            "group_vs_modules_rel_l2": max(rel_l2(a, b) for a, b in zip(fused, modules)),
            "group_vs_float64_rel_l2": max(rel_l2(a, b) for a, b in zip(fused, exact)),
            "out_dtype": str(fused[0].dtype),
        }
    return out


def build(spec, device, preset: str, method: str, variant: str = "full"):
    """The model quantized by `quantize_` (scope e2e) with the fused hooks (the Triton per-token kernel
    for the layers outside the sampler's groups, on CUDA): (model, report)."""
    model = spec.build(variant=variant, device=device, seed=0).eval()
    config = QuantConfig.from_preset(preset, scope="e2e", method=method)
    report = quantize_(model, config, config.select(model, spec.components))
    fuse_activation_hooks(report)
    return model, report


def layer_bytes(model, names) -> int:
    """Bytes of the storages behind the parameters and buffers of the layers `names` (each storage
    once: a merged group's members view one weight)."""
    storages = {}
    for name in names:
        for tensor in (*model.get_submodule(name).parameters(), *model.get_submodule(name).buffers()):
            storage = tensor.untyped_storage()
            storages[storage.data_ptr()] = storage.nbytes()
    return sum(storages.values())


def groups_summary(sampler: CapturedSampler) -> dict:
    groups = sampler._model_groups()
    every = [g for layer in groups.vision + groups.prefix + groups.expert for g in (layer.qkv, layer.out, layer.mlp_in, layer.mlp_out)]
    return {"total": len(every), "fused": sum(g.fused for g in every),
            "producer_cast": sum(getattr(g, "cast", None) is not None for g in every)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", required=True)
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 8, 32])
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--cameras", type=int, default=2)
    parser.add_argument("--checks-only", action="store_true", help="only the kernel checks (no model)")
    args = parser.parse_args()
    device = torch.device("cuda")
    results = {"machine": machine(), "cameras": args.cameras, "steps": STEPS, "batches": args.batches}
    results["checks"] = kernel_checks(device)
    print("checks:", json.dumps(results["checks"], indent=1), flush=True)
    if args.checks_only:
        Path(args.out).write_text(json.dumps(results, indent=1))
        return

    spec = get_model_spec("pi05")
    inputs = {b: chunk_inputs(b, device, seed=b, cameras=args.cameras) for b in args.batches}
    samplers, cells = {}, {}
    for name, (preset, method) in {**CELLS, **REFERENCE_CELLS}.items():
        torch.cuda.synchronize()
        before = torch.cuda.memory_allocated()
        t0 = time.perf_counter()
        model, report = build(spec, device, preset, method)
        sampler = CapturedSampler(model, num_steps=STEPS, graph_sizes=args.batches)
        groups = groups_summary(sampler)  # makes the linear groups (bf16: q/k/v and gate/up copies)
        torch.cuda.synchronize()
        cells[name] = {"preset": preset, "method": method, "format": report.result.format,
                       "build_s": time.perf_counter() - t0, "linear_groups": groups,
                       "model_and_groups_gib": (torch.cuda.memory_allocated() - before) / GiB,
                       "quantized_layers": len(report.result.hooks), "report": report}
        samplers[name] = sampler
        print(name, {k: v for k, v in cells[name].items() if k != "report"}, flush=True)

    # Weight memory of the quantized components: the e2e layers' storages, BF16 cell's as released.
    names = list(cells["fp8real"]["report"].result.hooks)
    weight_bytes = {name: layer_bytes(samplers[name].model, names) for name in ("bf16", *REAL_CELLS)}
    bf16_equivalent = sum(2 * t.numel() for n in names for t in samplers["bf16"].model.get_submodule(n).parameters())
    results["weight_memory"] = {
        "layers": len(names), "bf16_released_gib": weight_bytes["bf16"] / GiB,
        **{f"{n}_gib": weight_bytes[n] / GiB for n in REAL_CELLS},
        **{f"{n}_vs_bf16_released": weight_bytes[n] / weight_bytes["bf16"] for n in REAL_CELLS},
        **{f"{n}_vs_all_bf16": weight_bytes[n] / bf16_equivalent for n in REAL_CELLS},
        "model_and_groups_gib": {n: c["model_and_groups_gib"] for n, c in cells.items()},
    }
    print("weight memory:", results["weight_memory"], flush=True)
    write = lambda: Path(args.out).write_text(json.dumps(results, indent=1))  # noqa: E731
    write()  # after every stage: a run cut short by a time limit keeps what it measured

    # Actions on the same inputs (each form's graphs captured for the batch first).
    actions = {}
    for name, sampler in samplers.items():
        for other in samplers.values():
            other.reset()
        torch.cuda.empty_cache()
        actions[name] = {b: sampler(*inputs[b]).float() for b in (args.batches if name in CELLS else args.batches[:1])}
    results["actions_rel_l2"] = {
        f"{a}_vs_{b}": {bt: rel_l2(actions[a][bt], actions[b][bt]) for bt in actions[a].keys() & actions[b].keys()}
        for a, b in ACTION_PAIRS}
    print("actions rel L2:", results["actions_rel_l2"], flush=True)
    write()
    for name in REFERENCE_CELLS:  # timed no further: their memory goes back
        samplers.pop(name).reset()
    torch.cuda.empty_cache()

    ms = alternate(samplers, inputs, args.batches, args.repeats, args.rounds)
    results["chunk_ms"] = ms
    results["vs_bf16"] = {n: {b: ms[n][b] / ms["bf16"][b] for b in args.batches} for n in CELLS if n != "bf16"}
    results["rounds"], results["repeats_per_round"] = args.rounds, args.repeats
    print("chunk ms:", ms, "\nvs bf16:", results["vs_bf16"], flush=True)
    write()

    for name, cell in cells.items():
        report = cell.pop("report")
        cell["unfired_after_capture"] = report.unfired()
    results["cells"] = cells
    Path(args.out).write_text(json.dumps(results, indent=1))
    print("wrote", args.out)


if __name__ == "__main__":
    main()
