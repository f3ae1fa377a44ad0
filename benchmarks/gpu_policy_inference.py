"""pi0.5 per-chunk latency and throughput: eager lerobot vs the captured sampler, with and without
W4A8 / W4A4 end-to-end fake quantization, measured side by side in one process.

Model: lerobot 0.6.1 `PI05Pytorch` at full size, random weights, bf16 (lerobot keeps the SigLIP
tower, projector and norms in float32), 3 cameras at 224 px (`--cameras 2`: LIBERO's two, as the
released LIBERO checkpoint and every LIBERO cell has them), 200 prompt tokens, 10 flow steps.
Quantization: `vlaquantbench.quant.quantize_` with scope e2e (all 456 selectable linears); the
captured form swaps its hooks' transforms for the fused kernel (`quant.fused_kernel`).
Timing: CUDA-synchronized wall clock per chunk, warm-up discarded, median of the repeats.

    python benchmarks/gpu_policy_inference.py --out benchmarks/results/gpu_policy_inference.json
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time
from pathlib import Path

import torch

from vlaquantbench.models.pi05.fast import CapturedSampler
from vlaquantbench.quant.fused_kernel import fuse_activation_hooks
from vlaquantbench.models import get_model_spec
from vlaquantbench.quant import QuantConfig, quantize_, select_layers


def chunk_inputs(batch: int, device, seed: int = 0, cameras: int = 3):
    g = torch.Generator(device="cpu").manual_seed(seed)
    images = [(torch.rand(batch, 3, 224, 224, generator=g) * 2 - 1).to(device) for _ in range(cameras)]
    img_masks = [torch.ones(batch, dtype=torch.bool, device=device) for _ in range(cameras)]
    tokens = torch.randint(0, 257152, (batch, 200), generator=g).to(device)
    masks = torch.ones(batch, 200, dtype=torch.bool, device=device)
    noise = torch.randn(batch, 50, 32, generator=g).to(device)
    return images, img_masks, tokens, masks, noise


def time_chunks(fn, warmup: int, repeats: int) -> list[float]:
    sync = torch.cuda.synchronize if torch.cuda.is_initialized() else lambda: None  # CPU smoke runs: nothing to wait for
    for _ in range(warmup):
        fn()
    sync()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        sync()
        times.append(time.perf_counter() - start)
    return times


def fused_kernel_check(device) -> dict:
    """Fraction of elements where the fused kernel equals the reference transform (expected: all)."""
    from vlaquantbench.quant.fused_kernel import fused_fake_quant
    from vlaquantbench.quant.input_transform import InputTransform

    out = {}
    g = torch.Generator(device="cpu").manual_seed(0)
    for rows, cols, dtype in [(968, 2048, torch.bfloat16), (50, 16384, torch.bfloat16), (256, 1152, torch.float32)]:
        x = (torch.randn(rows, cols, generator=g) * torch.rand(rows, 1, generator=g) * 5).to(device, dtype)
        smooth = torch.rand(cols, generator=g).to(device) + 0.5
        clip = torch.rand(cols, generator=g).to(device) * 3 + 0.1
        for bits in (4, 8):
            for sm, cl in ((None, None), (smooth, clip)):
                ref = InputTransform(smooth=sm, clip=cl, act_bits=bits)(x)
                got = fused_fake_quant(x, bits, sm, cl)
                key = f"{rows}x{cols}_{str(dtype)[6:]}_a{bits}{'_smooth_clip' if sm is not None else ''}"
                out[key] = (got == ref).double().mean().item()
    return out


def binade_rows(device) -> torch.Tensor:
    """128 bf16 rows, one per bf16 absmax in [1, 2): every bf16 value of magnitude up to that absmax
    (the others zeroed), then the absmax itself."""
    values = (torch.arange(2 ** 16, dtype=torch.int32) << 16).view(torch.float32)
    values = values[values.isfinite() & (values.abs() <= 2)].sort().values
    absmaxes = 1 + torch.arange(128) / 128
    rows = torch.where(values.abs() <= absmaxes[:, None], values, 0.0)
    return torch.cat([rows, absmaxes[:, None]], dim=1).to(device, torch.bfloat16)


def fused_norm_quant_check(device) -> dict:
    """Fraction of elements where inductor's quantization fused into a norm (`models.pi05.fast.static_sampling`, the
    captured form's producers) equals `quant.grid` applied eagerly to the same input: the bare
    quantization compiled with the same options; the AdaRMS norm with its quantization fused against
    the compiled norm alone followed by eager quantization (the hooks' order) and against the eager
    norm (whose float32 reduction order differs, which moves row scales)."""
    from vlaquantbench.models.pi05.fast import static_sampling as pi05_static
    from vlaquantbench.quant.grid import fake_quant_activation
    from vlaquantbench.quant.hooks import quantizing_op

    g = torch.Generator(device="cpu").manual_seed(1)
    out = {}
    for bits in (4, 8):
        x = (torch.randn(4, 50, 1024, generator=g) * torch.rand(4, 50, 1, generator=g) * 8).to(device, torch.bfloat16)
        modulation = (torch.randn(4, 3 * 1024, generator=g) * 0.5).to(device, torch.bfloat16)
        bare = torch.compile(fake_quant_activation, dynamic=False, options=pi05_static._EAGER_NUMERICS)
        out[f"quant_a{bits}"] = (bare(x, bits) == fake_quant_activation(x, bits)).double().mean().item()
        # The quantization as the captured form's compiled ops write it (x / scale as `fma_quotient`),
        # on random rows and on every bf16 value up to each bf16 absmax of a binade (a row per absmax).
        as_compiled = quantizing_op(torch.clone, bits, pi05_static.inductor)
        for name, rows in (("random", x), ("binade", binade_rows(device))):
            out[f"quant_a{bits}_inductor_quotient_{name}"] = (
                as_compiled(rows) == fake_quant_activation(rows, bits)).double().mean().item()
        scale, shift = modulation[:, None, :1024], modulation[:, None, 1024:2048]
        fused = quantizing_op(pi05_static.ada_rms_norm, bits, pi05_static.inductor)(x, scale, shift, 1e-6)
        compiled_norm = pi05_static.COMPILED_OPS(pi05_static.ada_rms_norm, x, scale, shift, 1e-6)
        out[f"ada_rms_norm_quant_a{bits}_vs_compiled_norm"] = (fused == fake_quant_activation(compiled_norm, bits)).double().mean().item()
        eager = fake_quant_activation(pi05_static.ada_rms_norm(x, scale, shift, 1e-6), bits)
        out[f"ada_rms_norm_quant_a{bits}_vs_eager_norm"] = (fused == eager).double().mean().item()
        # The VLM's GELU product (968 x 16,384 values; a hand-written kernel, `gelu_quant`) and the
        # vision tower's float32 LayerNorm (compiled alone, then `quant.fused_kernel`'s quantization).
        gate, up = ((torch.randn(968, 16384, generator=g) * 2).to(device, torch.bfloat16) for _ in range(2))
        fused = quantizing_op(pi05_static.gelu_tanh_mul, bits, pi05_static.inductor)(gate, up)
        compiled_op = pi05_static.COMPILED_OPS(pi05_static.gelu_tanh_mul, gate, up)
        out[f"gelu_tanh_mul_quant_a{bits}_vs_compiled_op"] = (fused == fake_quant_activation(compiled_op, bits)).double().mean().item()
        out[f"gelu_tanh_mul_quant_a{bits}_vs_eager_op"] = (
            fused == fake_quant_activation(pi05_static.gelu_tanh_mul(gate, up), bits)).double().mean().item()
        # The vision tower's float32 GELU (768 x 4,304): its hand-written kernel too (`gelu_quant`).
        x32 = (torch.randn(768, 4304, generator=g) * 2).to(device)
        fused = quantizing_op(pi05_static.gelu_tanh, bits, pi05_static.inductor)(x32)
        out[f"gelu_tanh_quant_a{bits}_vs_eager_op"] = (
            fused == fake_quant_activation(pi05_static.gelu_tanh(x32), bits)).double().mean().item()
        h, upd = ((torch.randn(768, 1152, generator=g) * 3).to(device) for _ in range(2))
        w, b = (torch.randn(1152, generator=g).to(device) for _ in range(2))
        _, fused = quantizing_op(pi05_static.add_layer_norm, bits, pi05_static.inductor)(h, upd, w, b, 1e-6)
        _, compiled_op = pi05_static.COMPILED_OPS(pi05_static.add_layer_norm, h, upd, w, b, 1e-6)
        out[f"add_layer_norm_quant_a{bits}_vs_compiled_op"] = (fused == fake_quant_activation(compiled_op, bits)).double().mean().item()
    return out


def alternate(samplers: dict, inputs, batches, repeats: int, rounds: int) -> dict[str, dict[int, float]]:
    """Median captured chunk ms per sampler and batch, the samplers taking turns `rounds` times, so
    that drift of the machine falls on all of them alike. Each sampler's graphs are dropped after its
    turn (two forms' graphs at batch 1, 8 and 32 do not fit beside each other in 140 GiB) and
    captured again on its next turn, outside the timed calls."""
    times = {name: {b: [] for b in batches} for name in samplers}
    for _ in range(rounds):
        for name, s in samplers.items():
            for other in samplers.values():
                other.reset()
            torch.cuda.empty_cache()
            for b in batches:
                s(*inputs[b])  # capture
                times[name][b] += time_chunks(lambda: s(*inputs[b]), warmup=2, repeats=repeats)
    for s in samplers.values():
        s.reset()
    torch.cuda.empty_cache()
    return {name: {b: 1e3 * statistics.median(t) for b, t in by_b.items()} for name, by_b in times.items()}


def released_weights(model, spec) -> dict:
    """Copies of the weights of every layer a preset may round in place (scope e2e)."""
    return {n: m.weight.detach().clone() for n, m in select_layers(model, spec.components, "e2e", None, None).flat().items()}


def requantize(model, spec, originals: dict, preset: str):
    """The model's weights restored from `released_weights`, then quantized by `quantize_` (scope
    e2e) for `preset`: one model serves preset after preset. Returns the report (its hooks installed;
    remove them before the next preset)."""
    with torch.no_grad():
        for name, weight in originals.items():
            model.get_submodule(name).weight.copy_(weight)
    return _quantize(model, spec, preset)


def _quantize(model, spec, preset: str):
    config = QuantConfig.from_preset(preset, scope="e2e")
    return quantize_(model, config, config.select(model, spec.components))


def quantized_model(spec, device, preset: str):
    """A full-size model built as every cell of this script builds it, quantized by `quantize_`
    (scope e2e) with the fused hooks: (model, report)."""
    model = spec.build(variant="full", device=device, seed=0).eval()
    report = _quantize(model, spec, preset)
    fuse_activation_hooks(report)
    return model, report


def preset_ab(spec, device, presets, inputs, batches, steps, repeats, rounds) -> dict:
    """Captured chunk time of one model per preset (`quantized_model`, as the main loop quantizes),
    taking turns: the overhead of each preset against the first without the drift between one
    preset's timings and the next's (the main loop times them minutes apart)."""
    samplers, reports = {}, {}
    for preset in presets:
        model, reports[preset] = quantized_model(spec, device, preset)
        samplers[preset] = CapturedSampler(model, num_steps=steps, graph_sizes=batches)
    ms = alternate(samplers, inputs, batches, repeats, rounds)
    first = presets[0]
    return {"median_ms": ms, f"vs_{first}": {p: {b: ms[p][b] / ms[first][b] for b in batches} for p in presets[1:]},
            "hooks": {p: len(r.result.hooks) for p, r in reports.items()},
            "unfired_after_capture": {p: r.unfired() for p, r in reports.items()},
            "rounds": rounds, "repeats_per_round": repeats}


def inductor_cache_files() -> int:
    """Files in inductor's on-disk cache: 0 on a fresh machine, where the first captures compile
    every op (the warm-up times depend on it)."""
    from torch._inductor.runtime.cache_dir_utils import cache_dir

    return sum(1 for path in Path(cache_dir()).rglob("*") if path.is_file())


def machine() -> dict:
    import lerobot
    import transformers

    return {"gpu": torch.cuda.get_device_name(), "torch": torch.__version__, "cuda": torch.version.cuda,
            "python": platform.python_version(), "date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "lerobot": lerobot.__version__, "transformers": transformers.__version__}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", required=True)
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 8, 32])
    parser.add_argument("--presets", nargs="+", default=["BASELINE", "W4A8", "W4A4"])
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--cameras", type=int, default=3, help="camera images per observation (LIBERO: 2)")
    parser.add_argument("--eager-repeats-large", type=int, default=5, help="repeats for eager at batch >= 8")
    parser.add_argument("--preset-ab", type=int, default=0, metavar="ROUNDS",
                        help="only this: one captured model per preset, taking turns ROUNDS times (no eager timings "
                             "or checks)")
    args = parser.parse_args()

    device = torch.device("cuda")
    spec = get_model_spec("pi05")
    steps = 10
    setup = {"model": "pi05 PI05Pytorch full, random weights, bf16 (vision fp32 as lerobot)",
             "cameras": args.cameras, "image_px": 224, "prompt_tokens": 200, "flow_steps": steps,
             "repeats": args.repeats, "warmup": 3}
    if args.preset_ab:
        inputs = {b: chunk_inputs(b, device, cameras=args.cameras) for b in args.batches}
        ab = preset_ab(spec, device, args.presets, inputs, args.batches, steps, args.repeats, args.preset_ab)
        with open(args.out, "w") as f:
            json.dump({"preset_ab": ab, "machine": machine(), "setup": {**setup, "warmup": 2}}, f, indent=1)
        print(json.dumps(ab, indent=1))
        return
    cache_files_at_start = inductor_cache_files()
    t0 = time.perf_counter()
    model = spec.build(variant="full", device=device, seed=0).eval()
    build_s = time.perf_counter() - t0
    inputs = {b: chunk_inputs(b, device, cameras=args.cameras) for b in args.batches}
    originals = released_weights(model, spec)  # each cell rounds weights in place
    results = {"cells": [], "checks": {"fused_equal_fraction": fused_kernel_check(device)}}
    print("fused kernel == reference:", results["checks"]["fused_equal_fraction"], flush=True)
    results["checks"]["fused_norm_quant_equal_fraction"] = fused_norm_quant_check(device)
    print("norm-fused quantization == reference:", results["checks"]["fused_norm_quant_equal_fraction"], flush=True)

    for preset in args.presets:
        report = requantize(model, spec, originals, preset)
        cell = {"preset": preset, "format": report.result.format, "hooks": len(report.result.hooks),
                "layers": report.components, "eager": {}, "captured": {}}

        for b in args.batches:
            images, img_masks, tokens, masks, noise = inputs[b]
            reps = args.repeats if b == 1 else args.eager_repeats_large
            times = time_chunks(lambda: model.sample_actions(images, img_masks, tokens, masks, noise=noise.clone(),
                                                             num_steps=steps), warmup=3, repeats=reps)
            cell["eager"][b] = {"median_ms": 1e3 * statistics.median(times), "chunks_per_s": b / statistics.median(times)}
            print(f"[{preset}] eager b{b}: {1e3 * statistics.median(times):.1f} ms", flush=True)
        eager_hook_calls = sum(report.hook_calls().values())

        fused = fuse_activation_hooks(report)
        # One graph per measured batch size (not the closed loop's plans): a batch-32 chunk is one graph.
        sampler = CapturedSampler(model, num_steps=steps, graph_sizes=args.batches)
        for b in args.batches:
            images, img_masks, tokens, masks, noise = inputs[b]
            torch.cuda.synchronize()
            t0 = time.perf_counter()
            sampler(images, img_masks, tokens, masks, noise)
            torch.cuda.synchronize()
            capture_s = time.perf_counter() - t0
            times = time_chunks(lambda: sampler(images, img_masks, tokens, masks, noise), warmup=3, repeats=args.repeats)
            cell["captured"][b] = {"median_ms": 1e3 * statistics.median(times),
                                   "chunks_per_s": b / statistics.median(times), "capture_s": capture_s}
            print(f"[{preset}] captured b{b}: {1e3 * statistics.median(times):.2f} ms (capture {capture_s:.1f} s)",
                  flush=True)
        cell["fused_hooks"] = fused
        groups = sampler._groups
        layer_groups = [g for layer in groups.prefix + groups.expert for g in (layer.qkv, layer.out, layer.mlp_in, layer.mlp_out)]
        layer_groups += [g for layer in groups.vision for g in (layer.qkv, layer.out, layer.mlp_in, layer.mlp_out)]
        cell["linear_groups"] = {"fused": sum(g.fused for g in layer_groups), "total": len(layer_groups),
                                 "quantized_by_producer_or_group": sum(g.input_quantization is not None for g in layer_groups)}
        cell["unfired_after_capture"] = report.unfired()
        cell["hook_calls_eager_plus_capture"] = sum(report.hook_calls().values())
        cell["hook_calls_eager"] = eager_hook_calls

        if b_check := 1 if 1 in args.batches else None:
            images, img_masks, tokens, masks, noise = inputs[b_check]
            eager = model.sample_actions(images, img_masks, tokens, masks, noise=noise.clone(), num_steps=steps)
            captured = sampler(images, img_masks, tokens, masks, noise)
            rel = ((captured.float() - eager.float()).norm() / eager.float().norm()).item()
            cell["captured_vs_eager_rel_l2_b1"] = rel
            print(f"[{preset}] captured vs eager actions, relative L2: {rel:.2e}", flush=True)
        report.remove_hooks()
        results["cells"].append(cell)
        del sampler
        torch.cuda.empty_cache()

    results["machine"] = machine()
    results["model_build_s"] = build_s
    results["inductor_cache_files_at_start"] = cache_files_at_start
    results["setup"] = setup
    with open(args.out, "w") as f:
        json.dump(results, f, indent=1)
    print("wrote", args.out)


if __name__ == "__main__":
    main()
