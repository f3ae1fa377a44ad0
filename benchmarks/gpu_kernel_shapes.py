"""Where pi0.5's chunk time goes under each real kernel, and which tile pays: every linear product of a chunk by
shape, timed alone in each form, and the captured chunk's kernels by family (issue 51).

1. `products`: the linear products of one chunk (rows x in x out, dtype, how many), recorded by a dispatch mode
   on the eager run of the BF16 model (`CapturedSampler(use_graphs=False)`), at each batch. The component is read
   from the rows: 50 x batch the action expert, 256 x cameras x batch the vision tower, their sum + 200 prompt
   tokens the language model.
2. `shapes`: each distinct product timed alone (`triton.testing.do_bench_cudagraph`, median) as
   - `ref`: the released dtype's product (`torch.mm`, float32 with TF32 for SigLIP, else bf16);
   - `int8_cast`, `int8_mm`, `int8_rescale`: the three kernels of `Int8DynamicLinear` (the cast is fused into
     the producer in the captured chunk, the others are not);
   - `fp8_cast`, `fp8_mm`: `torch._scaled_mm` row-wise with fast accumulation;
   - `int4`: tinygemm (`torch._weight_int4pack_mm`, groups of 128, bf16 input);
   - `triton_int8`, `triton_fp8`, `triton_w4a16`: `quant.kernels.scaled_gemm`'s GEMMs at every tile of the
     kind's list (`--kinds`); the best tile, its time and its largest difference from the library's product
     (int8: equal; FP8: `torch._scaled_mm`; W4A16: the dequantized weights in float32).
   Chunk totals per component and form: the sum of count x time. The best tiles are then installed
   (`scaled_gemm.MEASURED_TILES`) for the cells of step 3.
3. `profile`: for each cell of `--cells` (one model at a time, BF16 first), the captured chunk's median time at
   each of `--profile-batches` and, at batch 1, its CUDA kernels' time by family under `torch.profiler`.
   Cells: those of `gpu_fp8_real.CELLS`, `fp8real_cublas` (every FP8 product on `torch._scaled_mm`) and the
   mixed assignments of `MIXED` (one method per component).

    python benchmarks/gpu_kernel_shapes.py --out benchmarks/results/gpu_kernel_shapes.json
    python benchmarks/gpu_kernel_shapes.py --sanitize int8real --out /tmp/s.json   # under compute-sanitizer
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from collections import Counter
from pathlib import Path

import torch
from torch.utils._python_dispatch import TorchDispatchMode

sys.path.insert(0, str(Path(__file__).resolve().parent))
from gpu_fp8_real import CELLS, STEPS, build  # noqa: E402
from gpu_policy_inference import chunk_inputs, machine, time_chunks  # noqa: E402

from vlaquantbench.models import get_model_spec  # noqa: E402
from vlaquantbench.models.pi05.fast import CapturedSampler  # noqa: E402
from vlaquantbench.quant import QuantConfig, quantize_  # noqa: E402
from vlaquantbench.quant.fused_kernel import fuse_activation_hooks  # noqa: E402
from vlaquantbench.quant.kernels.int8 import INT_MM_MIN_ROWS, dequantize_int32  # noqa: E402
from vlaquantbench.quant.kernels.packed import FP8, quantize_per_token  # noqa: E402
from vlaquantbench.quant.kernels import fp8 as fp8_kernels  # noqa: E402
from vlaquantbench.quant.kernels.scaled_gemm import MEASURED_TILES, Tile, pack_int4, scaled_gemm, w4a16_gemm  # noqa: E402

PRODUCT_OPS = {torch.ops.aten.mm.default: (0, 1), torch.ops.aten.addmm.default: (1, 2)}
TILES = [Tile(m, n, k, s, w) for m in (16, 32, 64) for n in (64, 128) for k in (128, 256) for s, w in ((3, 4),)]
TILES += [Tile(128, 128, 128, 3, 8), Tile(128, 256, 64, 3, 8), Tile(64, 256, 128, 3, 8), Tile(128, 128, 64, 4, 4)]
W4_TILES = [Tile(m, n, k) for m in (16, 32, 64) for n in (64, 128) for k in (64, 128)]  # k: PACK's multiple, divides 128
W4_TILES += [Tile(128, 128, 64, 3, 8), Tile(128, 256, 64, 3, 8), Tile(64, 256, 64, 3, 8), Tile(128, 128, 128, 3, 8)]
# One (preset, method, scope) per component group: int4 where the rows are few, FP8 or INT8 where they are many.
MIXED = {"int4_expert_fp8": (("W4", "int4wo", "ah"), ("W8A8", "fp8", "ve_mp_llm")),
         "int4_expert_int8": (("W4", "int4wo", "ah"), ("W8A8", "int8_dynamic", "ve_mp_llm")),
         "int4_llm_expert_fp8": (("W4", "int4wo", "llm"), ("W4", "int4wo", "ah"), ("W8A8", "fp8", "ve"))}
FAMILIES = (("int8 gemm", ("imma", "i8i8", "s8", "int8")), ("fp8 gemm", ("e4m3", "f8f8", "fp8", "qmma")),
            ("tinygemm", ("tinygemm", "int4")), ("triton gemm", ("_scaled_gemm",)), ("attention", ("fmha", "flash", "attention", "sdpa")),
            ("gemm", ("gemm", "sm90_xmma", "cutlass", "ampere", "sm80", "gemv", "Kernel2", "splitK")),
            ("triton", ("triton_",)))


class ProductRecorder(TorchDispatchMode):
    """Counts (rows, in, out, dtype) of every 2-D matrix product with a 2-D right operand."""

    def __init__(self):
        super().__init__()
        self.counts: Counter = Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        if func in PRODUCT_OPS:
            a, b = (args[i] for i in PRODUCT_OPS[func])
            if a.dim() == 2 and b.dim() == 2:
                self.counts[(a.shape[0], a.shape[1], b.shape[1], str(a.dtype)[6:])] += 1
        return func(*args, **(kwargs or {}))


def component(rows: int, batch: int, cameras: int) -> str:
    vision = 256 * cameras * batch
    return {50 * batch: "expert", vision: "vision", vision + 200 * batch: "llm"}.get(rows, "other")


def bench(fn) -> float:
    """Median microseconds of `fn` replayed from a CUDA graph (launch overhead excluded)."""
    import triton.testing

    fn()
    return 1e3 * triton.testing.do_bench_cudagraph(fn, rep=10, return_mode="median")


def best_tile(kind: str, tiles, run, reference) -> dict:
    """The fastest tile of `tiles` for `run(tile)`, with its largest difference from `reference`."""
    best, skipped = None, []
    for tile in tiles:
        try:
            got = run(tile)
            t = bench(lambda: run(tile))
        except Exception as error:  # noqa: BLE001 - a tile a shape cannot take (shared memory): skipped
            skipped.append(f"{tile.describe()}: {type(error).__name__}: {str(error)[:200]}")
            continue
        if best is None or t < best[0]:
            best = (t, tile, (got.float() - reference.float()).abs().max().item())
    out = {f"triton_{kind}_skipped": skipped} if skipped else {}
    if best:
        out |= {f"triton_{kind}": best[0], f"triton_{kind}_tile": best[1], f"triton_{kind}_max_abs_diff": best[2]}
    return out


def int4_case(x: torch.Tensor, n: int, g: torch.Generator):
    """Random int4 levels (n x K padded to 128, uint8), bf16 scales and zeros per group of 128, and x @ W^T with the
    dequantized weights rounded to bf16, as `w4a16_gemm` computes them."""
    k = x.shape[1]
    k_padded = -(-k // 128) * 128
    levels = torch.randint(0, 16, (n, k_padded), generator=g, dtype=torch.uint8).to(x.device)
    scales = (torch.rand(k_padded // 128, n, generator=g) * 0.02).to(x.device, torch.bfloat16)
    zeros = (torch.randn(k_padded // 128, n, generator=g) * 0.02).to(x.device, torch.bfloat16)
    weight = (levels.float() - 8) * scales.float().repeat_interleave(128, 0).t() + zeros.float().repeat_interleave(128, 0).t()
    return levels, scales, zeros, x.to(torch.bfloat16).float() @ weight.to(torch.bfloat16).float()[:, :k].t()


def time_shape(m: int, k: int, n: int, dtype: str, device, kinds) -> dict:
    g = torch.Generator(device="cpu").manual_seed(m * 7 + k * 3 + n)
    x = torch.randn(m, k, generator=g).to(device, getattr(torch, dtype))
    linear = torch.nn.Linear(k, n, bias=False, device=device, dtype=torch.bfloat16)
    weight = linear.weight.to(x.dtype)
    torch.backends.cuda.matmul.allow_tf32 = True  # as the captured sampler computes SigLIP's float32 products
    out = {"ref": bench(lambda: torch.mm(x, weight.t()))}
    padded = max(INT_MM_MIN_ROWS, (m + 7) // 8 * 8)
    for name, dtype_q in (("int8", torch.int8), ("fp8", FP8)):
        q, s = quantize_per_token(x, dtype_q)
        wq, ws = quantize_per_token(linear.weight.detach().float(), dtype_q)
        ws = ws.reshape(1, -1).contiguous()
        out[f"{name}_cast"] = bench(lambda: quantize_per_token(x, dtype_q))
        if dtype_q == torch.int8:
            qp = torch.nn.functional.pad(q, (0, 0, 0, padded - m))
            acc = torch._int_mm(qp, wq.t())[:m]
            out["int8_mm"] = bench(lambda: torch._int_mm(qp, wq.t()))
            out["int8_rescale"] = bench(lambda: dequantize_int32(acc, s, ws, torch.bfloat16))
            reference = dequantize_int32(acc, s, ws, torch.bfloat16)
        else:
            out["fp8_mm"] = bench(lambda: torch._scaled_mm(q, wq.t(), scale_a=s, scale_b=ws, out_dtype=torch.bfloat16,
                                                           use_fast_accum=True))
            reference = torch._scaled_mm(q, wq.t(), scale_a=s, scale_b=ws, out_dtype=torch.bfloat16)
        if name in kinds:
            out |= best_tile(name, TILES, lambda tile: scaled_gemm(q, wq.t(), s, ws, torch.bfloat16, tile), reference)
    levels, scales, zeros, reference = int4_case(x, n, g)
    if "w4a16" in kinds:
        out |= best_tile("w4a16", W4_TILES, lambda tile: w4a16_gemm(x, pack_int4(levels), scales, zeros, 128,
                                                                      torch.bfloat16, tile), reference)
    if k % 128 == 0:
        xb = x.to(torch.bfloat16)
        packed = torch._convert_weight_to_int4pack((levels[:, ::2] << 4 | levels[:, 1::2]).contiguous(), 8)
        scales_zeros = torch.stack([scales, zeros], dim=-1).contiguous()
        out["tinygemm"] = bench(lambda: torch._weight_int4pack_mm(xb, packed, 128, scales_zeros))
    return out


def record_products(spec, device, batches, cameras) -> dict[int, Counter]:
    model = spec.build(variant="full", device=device, seed=0).eval()
    sampler = CapturedSampler(model, num_steps=STEPS, use_graphs=False, fuse_elementwise=False)
    found = {}
    for b in batches:
        recorder = ProductRecorder()
        with torch.no_grad(), recorder:
            sampler(*chunk_inputs(b, device, seed=b, cameras=cameras))
        found[b] = recorder.counts
    del sampler, model
    torch.cuda.empty_cache()
    return found


def family(name: str) -> str:
    lowered = name.lower()
    for label, keys in FAMILIES:
        if any(key.lower() in lowered for key in keys):
            return label
    return "other"


def build_cell(spec, device, cell: str, variant: str = "full"):
    """The model of `cell`: a `gpu_fp8_real.CELLS` cell, `fp8real_cublas` or a `MIXED` assignment."""
    if cell in CELLS or cell == "fp8real_cublas":
        preset, method = CELLS["fp8real" if cell == "fp8real_cublas" else cell]
        return build(spec, device, preset, method, variant)[0]
    model = spec.build(variant=variant, device=device, seed=0).eval()
    for preset, method, scope in MIXED[cell]:
        config = QuantConfig.from_preset(preset, scope=scope, method=method)
        fuse_activation_hooks(quantize_(model, config, config.select(model, spec.components)))
    return model


def profile_cell(spec, device, cell: str, cameras: int, repeats: int, batches) -> dict:
    fp8_kernels.TRITON_MAX_ROWS = 0 if cell == "fp8real_cublas" else DEFAULT_FP8_ROWS
    model = build_cell(spec, device, cell)
    sampler = CapturedSampler(model, num_steps=STEPS, graph_sizes=batches)
    out = {"chunk_ms": {}}
    for b in batches:
        inputs = chunk_inputs(b, device, seed=b, cameras=cameras)
        sampler(*inputs)  # capture
        out["chunk_ms"][b] = 1e3 * statistics.median(time_chunks(lambda: sampler(*inputs), warmup=2, repeats=repeats))
    inputs = chunk_inputs(1, device, seed=1, cameras=cameras)
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CUDA]) as prof:
        for _ in range(3):
            sampler(*inputs)
        torch.cuda.synchronize()
    kernels: Counter = Counter()
    by_family: Counter = Counter()
    for event in prof.key_averages():
        us = event.device_time_total / 3
        if us > 0:
            kernels[event.key[:120]] += us
            by_family[family(event.key)] += us
    out["actions_b1"] = sampler(*inputs).float().cpu()
    out |= {"kernel_us_by_family": dict(by_family.most_common()), "top_kernels_us": dict(kernels.most_common(12))}
    sampler.reset()
    del sampler, model
    torch.cuda.empty_cache()
    fp8_kernels.TRITON_MAX_ROWS = DEFAULT_FP8_ROWS
    return out


def sanitize(spec, device, cell: str, cameras: int, variant: str) -> dict:
    """One eager chunk of `cell` (the captured path's compiled ops, no graph) at batch 1 and 2, at `variant`'s
    widths; with cell `kernels`, the Triton GEMMs on odd shapes against their references. Run under
    `compute-sanitizer --tool memcheck` with PYTORCH_NO_CUDA_MEMORY_CACHING=1, so that every tensor is its own
    allocation and a read past one is reported."""
    out = {}
    if cell == "kernels":
        for m, k, n in ((1, 1152, 96), (3, 4304, 1152), (50, 1024, 2560), (77, 2048, 1000), (712, 300, 64)):
            g = torch.Generator(device="cpu").manual_seed(m + k + n)
            x = torch.randn(m, k, generator=g).to(device, torch.bfloat16)
            linear = torch.nn.Linear(k, n, bias=False, device=device, dtype=torch.bfloat16)
            for dtype_q in (torch.int8, FP8):
                q, s = quantize_per_token(x, dtype_q)
                wq, ws = quantize_per_token(linear.weight.detach().float(), dtype_q)
                ref = (q.float() @ wq.float().t()) * s * ws.reshape(1, -1)
                for tile in (Tile(16, 64, 128), Tile(16, 64, 128, 4, 4, 4), Tile(64, 128, 256), Tile(128, 128, 128, 3, 8)):
                    got = scaled_gemm(q, wq.t(), s, ws, torch.float32, tile)
                    out[f"{m}x{k}x{n} {str(dtype_q)[6:]} {tile.describe()}"] = (got - ref).abs().max().item() / ref.abs().max().item()
            levels, scales, zeros, ref = int4_case(x, n, g)
            for tile in (Tile(16, 64, 64), Tile(16, 64, 128, 4, 4, 4), Tile(64, 128, 128), Tile(128, 128, 64, 3, 8)):
                got = w4a16_gemm(x, pack_int4(levels), scales, zeros, 128, torch.float32, tile)
                out[f"{m}x{k}x{n} w4a16 {tile.describe()}"] = (got - ref).abs().max().item() / ref.abs().max().item()
        torch.cuda.synchronize()
        return out
    model = build_cell(spec, device, cell, variant)
    sampler = CapturedSampler(model, num_steps=STEPS, use_graphs=False)
    for b in (1, 2):
        actions = sampler(*chunk_inputs(b, device, seed=b, cameras=cameras))
        torch.cuda.synchronize()
        out[b] = {"finite": bool(actions.isfinite().all()), "shape": list(actions.shape)}
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", required=True)
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 8])
    parser.add_argument("--kinds", nargs="*", default=["int8", "fp8", "w4a16"], help="Triton GEMMs whose tiles are swept")
    parser.add_argument("--cameras", type=int, default=2)
    parser.add_argument("--cells", nargs="*", default=["bf16", "int8real", "fp8real", "fp8real_cublas", "int4", *MIXED])
    parser.add_argument("--profile-batches", type=int, nargs="+", default=[1, 8, 32])
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--sanitize", choices=[*sorted(CELLS), *MIXED, "kernels"], help="only one eager chunk of this cell")
    parser.add_argument("--variant", default="full", help="the widths of --sanitize's model (demo: small)")
    parser.add_argument("--skip-shapes", action="store_true")
    args = parser.parse_args()
    device = torch.device("cuda")
    spec = get_model_spec("pi05")
    results = {"machine": machine(), "cameras": args.cameras, "steps": STEPS}
    write = lambda: Path(args.out).write_text(json.dumps(results, indent=1, default=str))  # noqa: E731
    if args.sanitize:
        results["sanitize"] = {args.sanitize: sanitize(spec, device, args.sanitize, args.cameras, args.variant)}
        print(results["sanitize"], flush=True)
        write()
        return
    if not args.skip_shapes:
        t0 = time.perf_counter()
        found = record_products(spec, device, args.batches, args.cameras)
        shapes, totals = {}, {}
        for b, counts in found.items():
            for (m, k, n, dtype), count in sorted(counts.items()):
                key = f"b{b} {m}x{k}x{n} {dtype}"
                timed = time_shape(m, k, n, dtype, device, args.kinds)
                for kind in args.kinds:
                    if f"triton_{kind}_tile" in timed:
                        MEASURED_TILES[(kind, m, k, n)] = timed[f"triton_{kind}_tile"]
                shapes[key] = {"batch": b, "component": component(m, b, args.cameras), "count": count, **timed}
                print(key, {k: (round(v, 1) if isinstance(v, float) else v) for k, v in shapes[key].items()
                            if not k.endswith("skipped")}, flush=True)
                total = totals.setdefault(f"b{b}", {}).setdefault(shapes[key]["component"], Counter())
                for form, us in timed.items():
                    if isinstance(us, float) and not form.endswith("diff"):
                        total[form] += count * us / 1e3
                results["shapes"], results["chunk_ms_by_component"] = shapes, totals
                write()
        results["shapes_s"] = time.perf_counter() - t0
        print("chunk ms by component:", json.dumps(totals, indent=1), flush=True)
    results["profile"], actions = {}, {}
    for cell in args.cells:
        profiled = profile_cell(spec, device, cell, args.cameras, args.repeats, args.profile_batches)
        actions[cell] = profiled.pop("actions_b1")
        profiled["actions_rel_l2_vs_bf16"] = ((actions[cell] - actions["bf16"]).norm() / actions["bf16"].norm()).item()
        results["profile"][cell] = profiled
        print(cell, json.dumps(profiled, indent=1), flush=True)
        write()
    write()
    print("wrote", args.out)


DEFAULT_FP8_ROWS = fp8_kernels.TRITON_MAX_ROWS

if __name__ == "__main__":
    main()
