"""pi0.5 W4A4 with Hadamard rotations inside the captured chunk (issue 31, item 8): chunk time of
BASELINE, plain W4A4 fake quantization and W4A4 + Hadamard, side by side in one process, at batch
1, 8 and 32 with 2 cameras.

Cells (all captured, `CapturedSampler`; lerobot 0.6.1 `PI05Pytorch` at full size, random weights
seed 0, 2 cameras at 224 px, 200 prompt tokens, 10 flow steps; scope e2e, all 456 linears):
    baseline        BASELINE (bf16, the SigLIP tower and projector float32)
    w4a4            rtn-W4A4-e2e: the fused per-token quantization of every linear's input
    w4a4_hadamard   hadamard-W4A4-e2e: every linear's input rotated by its block-Hadamard transform
                    (`quant.transforms.BlockHadamard`) and quantized per token by one Triton kernel
                    after the op that produces it (`quant.fused_kernel.rotated_fake_quant`: products
                    with the +-1 Hadamard factors on the tensor cores); once per input that q/k/v or
                    gate/up share (`quant.hooks.Rotated`)
Also recorded: the linear groups the captured sampler fused, every hook's count after capture, the
actions of each cell against BASELINE, and the Hadamard cell's captured chunk against lerobot's eager
`sample_actions` of the same quantized model (batch 1; `models.adapter.CUDA_PROBE_BOUND` is 0.05).
Timing: `gpu_policy_inference.alternate` (the cells take turns `--rounds` times, each turn capturing
again), median of the repeats: the typical chunk, not the best.
Checks and breakdown: the rotation kernel against the reference transform on CUDA (fraction of equal
values, largest difference over the row's absmax; TF32 off, the hook's float32 products); each
rotated width's kernel time at batch 1 and 32 token counts, in a CUDA graph, against the unrotated
quantization kernel, and the ops that produce a rotated input, fused with it, against plain W4A4's
forms (`rotation_kernel_us`); kernel profiles (`kernel_profile`, the captured code
without its graph) of the two W4A4 cells at batch 1 and 32.

    python benchmarks/gpu_hadamard_captured.py --out benchmarks/results/gpu_hadamard_captured.json   # ~6 min, H200
    python benchmarks/gpu_hadamard_captured.py --device cpu --smoke --out /tmp/h.json   # demo widths, CPU, inductor
"""

from __future__ import annotations

import argparse
import functools
import json
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from gpu_fp8_real import groups_summary, rel_l2  # noqa: E402
from gpu_gelu_quant import graph_us as gelu_graph_us  # noqa: E402
from gpu_policy_inference import alternate, chunk_inputs, kernel_profile, machine, uncaptured_chunk  # noqa: E402

from vlaquantbench.models import get_model_spec  # noqa: E402
from vlaquantbench.models.pi05.fast import CapturedSampler  # noqa: E402
from vlaquantbench.quant import QuantConfig, quantize_  # noqa: E402
from vlaquantbench.quant.fused_kernel import fuse_activation_hooks, fused_fake_quant, rotated_fake_quant  # noqa: E402
from vlaquantbench.quant.hadamard import BlockHadamard  # noqa: E402
from vlaquantbench.quant.hooks import Rotated  # noqa: E402
from vlaquantbench.quant.input_transform import InputTransform  # noqa: E402

CELLS = {"baseline": ("BASELINE", "rtn"), "w4a4": ("W4A4", "rtn"), "w4a4_hadamard": ("W4A4", "hadamard")}


def build(spec, device, variant: str, preset: str, method: str):
    model = spec.build(variant=variant, device=device, seed=0).eval()
    config = QuantConfig.from_preset(preset, scope="e2e", method=method)
    report = quantize_(model, config, config.select(model, spec.components))
    fuse_activation_hooks(report)  # the Triton per-token kernel for the layers outside the groups (CUDA)
    return model, report


# (tokens, width, dtype) of the rotated inputs at batch 1 and 32 (2 cameras, 200 prompt tokens, 50
# actions): SigLIP (float32 in lerobot) 1,152 and fc2's 4,304; Gemma 2,048 and down_proj's 16,384;
# the expert's 1,024, 2,048 (o_proj) and 4,096.
ROTATED_SHAPES = [(tokens * b, width, dtype) for b in (1, 32) for tokens, width, dtype in (
    (512, 1152, torch.float32), (512, 4304, torch.float32), (712, 2048, torch.bfloat16),
    (712, 16384, torch.bfloat16), (50, 1024, torch.bfloat16), (50, 2048, torch.bfloat16),
    (50, 4096, torch.bfloat16))]


def rotation_kernel_check(device) -> dict:
    """Per shape and bit width: the fraction of values where `rotated_fake_quant` equals the hooks'
    `InputTransform(rotation=BlockHadamard, act_bits)` (bf16: expected all but the rare value whose
    float32 rotation, summed in another order, rounds the other way), and the largest difference over
    its row's absmax (float32 rows: float32 rounding of the rotation, ~1e-7)."""
    out = {}
    g = torch.Generator(device="cpu").manual_seed(0)
    tf32 = torch.backends.cuda.matmul.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = False  # the hook's rotation: float32 products
    try:
        for rows, cols, dtype in [(968, 2048, torch.bfloat16), (50, 16384, torch.bfloat16), (50, 1024, torch.bfloat16),
                                  (50, 4096, torch.bfloat16), (512, 1152, torch.bfloat16), (512, 1152, torch.float32),
                                  (512, 4304, torch.float32)]:
            x = (torch.randn(rows, cols, generator=g) * torch.rand(cols, generator=g) * 5).to(device, dtype)
            rotation = BlockHadamard(cols, device)
            for bits in (4, 8):
                ref = InputTransform(rotation=rotation, act_bits=bits)(x)
                got = rotated_fake_quant(x, rotation, bits)
                absmax = ref.float().abs().amax(-1, keepdim=True).clamp_min(1e-30)
                out[f"{rows}x{cols}_{str(dtype)[6:]}_a{bits}"] = {
                    "equal_fraction": (got == ref).double().mean().item(),
                    "max_diff_over_absmax": ((got.float() - ref.float()).abs() / absmax).max().item()}
    finally:
        torch.backends.cuda.matmul.allow_tf32 = tf32
    return out


def graph_us(fn) -> float:
    """Microseconds per call of `fn` as the captured chunk runs it (`gpu_gelu_quant.graph_us`: calls
    captured in one CUDA graph, the median replay)."""
    return gelu_graph_us(fn, ())


def shared_tokens(cols: int, rotation: BlockHadamard) -> list[int]:
    """The tokens per program above one that `rotation_tile` allows for rows of `cols`."""
    from vlaquantbench.quant.fused_kernel import MAX_SHARED_TILE_ROWS, rotation_tile

    tile_rows = rotation_tile(cols, rotation)["TILE_ROWS"]
    return [t for t in (2, 4, 8) if t * tile_rows <= MAX_SHARED_TILE_ROWS]


def rotation_kernel_us(device) -> dict:
    """Microseconds per call inside a CUDA graph (`graph_us`), per rotated shape (`ROTATED_SHAPES`):
    the rotation kernel with its own choice of warps and with 4, 8 and 16, with several tokens per
    program (`shared_tokens`), and the unrotated per-token kernel (`fused_fake_quant`). Then the action expert's ops that produce a rotated input, at batch
    1 and 32, each as plain W4A4 runs it (the op and its quantization compiled by inductor, or the
    GELU kernel), as two kernels (the op compiled, then `rotated_fake_quant`) and as one
    (`rotated_norms`, `gelu_rotated_fake_quant`) with its own and with other warps."""
    from vlaquantbench.models.pi05.fast import gelu_quant, rotated_norms
    from vlaquantbench.models.pi05.fast import static_sampling as ss
    from vlaquantbench.quant.hooks import quantizing_op

    # The ops compiled alone, once, as code objects of their own: compiling the sampler's own
    # functions again here would count against their recompile limit, and past it the cells'
    # chunks would run those ops uncompiled.
    def norm_alone(*args):
        return ss.gated_add_ada_rms_norm(*args)

    def merge_alone(heads):
        return ss.merge_heads(heads)

    norm_compiled, merge_compiled = ss.inductor(norm_alone), ss.inductor(merge_alone)

    out = {}
    for rows, cols, dtype in ROTATED_SHAPES:
        x = torch.randn(rows, cols, device=device).to(dtype)
        rotation = BlockHadamard(cols, device)
        forms = {"rotated_kernel": lambda: rotated_fake_quant(x, rotation, 4),
                 **{f"rotated_kernel_{w}_warps": functools.partial(rotated_fake_quant, x, rotation, 4, num_warps=w)
                    for w in (4, 8, 16)},
                 **{f"rotated_kernel_{t}_tokens": functools.partial(rotated_fake_quant, x, rotation, 4,
                                                                    tokens_per_program=t)
                    for t in shared_tokens(cols, rotation)},
                 "unrotated_kernel": lambda: fused_fake_quant(x, 4)}
        out[f"{rows}x{cols}_{str(dtype)[6:]}"] = {name: graph_us(fn) for name, fn in forms.items()}
    for batch in (1, 32):
        g = torch.Generator(device="cpu").manual_seed(batch)
        rand = lambda *shape: torch.randn(*shape, generator=g).to(device)  # noqa: E731
        hidden, update = rand(batch, 50, 1024).bfloat16(), rand(batch, 50, 1024).bfloat16()
        scale, shift, gate = rand(batch, 1, 3 * 1024).mul(0.3).chunk(3, dim=-1)
        gate = gate.bfloat16()
        heads = rand(batch, 8, 50, 256).bfloat16()
        gate_up = rand(batch, 50, 2 * 4096).bfloat16()
        mlp_gate, mlp_up = gate_up[..., :4096], gate_up[..., 4096:]
        r1024, r2048, r4096 = (BlockHadamard(w, device) for w in (1024, 2048, 4096))
        norm_args = (hidden, update, gate, scale, shift, 1e-6)
        ops = {
            "gated_add_ada_rms_norm": {
                "w4a4_compiled": functools.partial(quantizing_op(norm_alone, 4, ss.inductor), *norm_args),
                "rotated_two_kernels": lambda: rotated_fake_quant(norm_compiled(*norm_args)[1], r1024, 4),
                **{f"rotated_fused_{w or 'own'}_warps": functools.partial(
                    rotated_norms.gated_add_ada_rms_norm_rotated_fake_quant, *norm_args, rotation=r1024, bits=4,
                    num_warps=w) for w in (None, 2, 8, 16)},
                **{f"rotated_fused_{t}_tokens": functools.partial(
                    rotated_norms.gated_add_ada_rms_norm_rotated_fake_quant, *norm_args, rotation=r1024, bits=4,
                    tokens_per_program=t) for t in shared_tokens(1024, r1024)}},
            "merge_heads": {
                "w4a4_compiled": functools.partial(quantizing_op(merge_alone, 4, ss.inductor), heads),
                "rotated_two_kernels": lambda: rotated_fake_quant(merge_compiled(heads), r2048, 4),
                **{f"rotated_fused_{w or 'own'}_warps": functools.partial(
                    rotated_norms.merge_heads_rotated_fake_quant, heads, rotation=r2048, bits=4, num_warps=w)
                   for w in (None, 2, 8, 16)},
                **{f"rotated_fused_{t}_tokens": functools.partial(
                    rotated_norms.merge_heads_rotated_fake_quant, heads, rotation=r2048, bits=4, tokens_per_program=t)
                   for t in shared_tokens(2048, r2048)}},
            "gelu_tanh_mul": {
                "w4a4_kernel": lambda: gelu_quant.gelu_fake_quant(mlp_gate, mlp_up, 4),
                **{f"rotated_fused_{w or 'own'}_warps": functools.partial(
                    gelu_quant.gelu_rotated_fake_quant, mlp_gate, mlp_up, r4096, 4, num_warps=w)
                   for w in (None, 8, 16, 32)},
                **{f"rotated_fused_{t}_tokens": functools.partial(
                    gelu_quant.gelu_rotated_fake_quant, mlp_gate, mlp_up, r4096, 4, tokens_per_program=t)
                   for t in shared_tokens(4096, r4096)}},
        }
        for op, forms in ops.items():
            out[f"expert_{op}_b{batch}"] = {name: graph_us(fn) for name, fn in forms.items()}
    for rows in (712, 22784):  # the VLM's down_proj input at batch 1 and 32 (2 cameras, 200 prompt tokens)
        gate_up = torch.randn(rows, 2 * 16384, device=device).bfloat16()
        mlp_gate, mlp_up, r16384 = gate_up[:, :16384], gate_up[:, 16384:], BlockHadamard(16384, device)
        out[f"vlm_gelu_tanh_mul_{rows}"] = {
            "w4a4_kernel": graph_us(lambda: gelu_quant.gelu_fake_quant(mlp_gate, mlp_up, 4)),
            "rotated_fused": graph_us(lambda: gelu_quant.gelu_rotated_fake_quant(mlp_gate, mlp_up, r16384, 4))}
    return out


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

    if device.type == "cuda":
        results["rotation_kernel_equal"] = rotation_kernel_check(device)
        print("rotation kernel == reference:", results["rotation_kernel_equal"], flush=True)
        results["rotation_kernel_us"] = rotation_kernel_us(device)
        for shape, forms in results["rotation_kernel_us"].items():
            print("us per call in a graph", shape, {name: round(us, 2) for name, us in forms.items()}, flush=True)
        write()

    spec = get_model_spec("pi05")
    inputs = {b: chunk_inputs(b, device, seed=b, cameras=args.cameras) for b in args.batches}
    samplers, cells, reports = {}, {}, {}
    for name, (preset, method) in CELLS.items():
        t0 = time.perf_counter()
        model, report = build(spec, device, variant, preset, method)
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

    if device.type == "cuda":  # where the time goes: the captured code's kernels, without the graph
        results["profiles"] = {}
        for name in ("w4a4", "w4a4_hadamard"):
            sampler = samplers[name]
            for b in (args.batches[0], args.batches[-1]):
                sampler(*inputs[b])
                with sampler._kernel_choices():
                    results["profiles"][f"{name}_b{b}"] = kernel_profile(uncaptured_chunk(sampler.model, sampler, inputs[b]))
                sampler.reset()
                print(name, b, "profile:", results["profiles"][f"{name}_b{b}"], flush=True)
        results["wall_s"] = time.perf_counter() - started
        write()
    print("wrote", args.out)


if __name__ == "__main__":
    main()
