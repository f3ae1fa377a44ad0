"""Floating-point format fake quantization inside the captured pi0.5 sampler: chunk latency of each
format next to integer W4A4 (and the baseline), measured side by side in one process.

Model and inputs as `gpu_policy_inference.py` (full-size `PI05Pytorch`, random weights, bf16 layout,
3 cameras at 224 px, 200 prompt tokens, 10 flow steps). Per preset: `quantize_` with scope e2e, the
integer presets' hooks swapped for the fused Triton kernel (`fuse_activation_hooks`; float formats
keep their reference transform, which runs through the member layers' hooks and is recorded into
the chunk's CUDA graph), then `CapturedSampler` chunks at each batch size. Reported per preset: median
ms per chunk, the ratio to W4A4 and to the baseline, hooks unfired after capture (must be 0), and the
captured-vs-eager relative L2 of the batch-1 chunk. A second table times one activation quantization
per format on typical linear-input shapes, eager and under `torch.compile`, next to the int4 kernel.

Real kernels: the script records the device's compute capability and whether block-scaled products
exist for it: FP8 (`torch._scaled_mm`, row-wise or tensor-wise scales) runs on Hopper (sm90);
MXFP8 / MXFP4 / NVFP4 matrix products with E8M0 / E4M3 block scales need Blackwell (sm100) tensor
cores (`torch._scaled_mm` with blocked scales, torchao `MXTensor` / `NVFP4Tensor`). On Hopper these
formats are fake-quantized only; the probe tries torchao's NVFP4 and MXFP8 linear and records the error.

    python benchmarks/gpu_formats.py --out benchmarks/results/gpu_formats.json
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time

import torch
from gpu_policy_inference import chunk_inputs, released_weights, requantize, time_chunks

from vlaquantbench.models import get_model_spec
from vlaquantbench.models.pi05.fast import CapturedSampler
from vlaquantbench.quant.fused_kernel import fused_fake_quant, fuse_activation_hooks
from vlaquantbench.quant.presets import FORMATS

PRESETS = ["BASELINE", "W4A4", "MXFP4", "NVFP4", "FP8E4M3", "FP8E4M3PT", "MXFP8E4M3", "MXFP6E2M3", "W4AMXFP4"]
# (rows, features) of typical linear inputs: action expert at batch 1, VLM prefix at batch 8
SHAPES = [(1, 50, 1024), (8, 968, 2048)]


def block_scaled_probe(device) -> dict:
    """Whether torchao's real MXFP8 / NVFP4 linear runs on this device (Blackwell), with the error if not."""
    probe = {"capability": list(torch.cuda.get_device_capability(device))}
    for name, make in (("mxfp8", _mx_config), ("nvfp4", _nvfp4_config)):
        linear = torch.nn.Sequential(torch.nn.Linear(1024, 1024, bias=False)).to(device, torch.bfloat16)
        try:
            from torchao.quantization import quantize_ as ao_quantize

            ao_quantize(linear, make())
            linear(torch.randn(32, 1024, device=device, dtype=torch.bfloat16))
            torch.cuda.synchronize()
            probe[name] = "ran"
        except Exception as err:  # noqa: BLE001 - recorded: which formats this GPU cannot run natively
            probe[name] = f"{type(err).__name__}: {str(err)[:200]}"
    return probe


def _mx_config():
    from torchao.prototype.mx_formats import MXDynamicActivationMXWeightConfig

    return MXDynamicActivationMXWeightConfig()


def _nvfp4_config():
    from torchao.prototype.mx_formats import NVFP4DynamicActivationNVFP4WeightConfig

    return NVFP4DynamicActivationNVFP4WeightConfig()


def activation_kernels(device, repeats: int) -> dict:
    """Median microseconds of one activation fake quantization per format and shape."""
    out = {}
    for shape in SHAPES:
        x = torch.randn(*shape, device=device, dtype=torch.bfloat16)
        row = {"int4_per_token_fused_triton": lambda: fused_fake_quant(x, 4)}
        for name in ("MXFP4", "NVFP4", "FP8E4M3", "MXFP8E4M3"):
            fmt = FORMATS[name]
            row[f"{name}_eager"] = lambda fmt=fmt: fmt.quantize_activation(x)
            compiled = torch.compile(fmt.quantize_activation, dynamic=False)
            row[f"{name}_compiled"] = lambda compiled=compiled: compiled(x)
        out["x".join(map(str, shape))] = {k: 1e6 * statistics.median(time_chunks(fn, warmup=3, repeats=repeats))
                                          for k, fn in row.items()}
        print(shape, json.dumps(out["x".join(map(str, shape))]), flush=True)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", required=True)
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 8])
    parser.add_argument("--presets", nargs="+", default=PRESETS)
    parser.add_argument("--repeats", type=int, default=10)
    args = parser.parse_args()

    device = torch.device("cuda")
    spec = get_model_spec("pi05")
    model = spec.build(variant="full", device=device, seed=0).eval()
    steps = 10
    inputs = {b: chunk_inputs(b, device) for b in args.batches}
    originals = released_weights(model, spec)
    results = {"device": torch.cuda.get_device_name(device), "torch": torch.__version__,
               "python": platform.python_version(), "date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
               "block_scaled_real_kernels": block_scaled_probe(device),
               "activation_quant_us": activation_kernels(device, args.repeats), "cells": {}}
    print("real block-scaled kernels:", results["block_scaled_real_kernels"], flush=True)

    for preset in args.presets:
        report = requantize(model, spec, originals, preset)
        fuse_activation_hooks(report)  # integer per-token transforms only; float formats fall back to theirs
        sampler = CapturedSampler(model, num_steps=steps, graph_sizes=args.batches)  # one graph per batch timed
        cell = {"format": report.result.format, "hooks": len(report.result.hooks), "captured_ms": {}}
        for b in args.batches:
            images, img_masks, tokens, masks, noise = inputs[b]
            t0 = time.perf_counter()
            sampler(images, img_masks, tokens, masks, noise)
            torch.cuda.synchronize()
            cell.setdefault("capture_s", {})[b] = time.perf_counter() - t0
            times = time_chunks(lambda: sampler(images, img_masks, tokens, masks, noise), warmup=3, repeats=args.repeats)
            cell["captured_ms"][b] = 1e3 * statistics.median(times)
            print(f"[{preset}] captured b{b}: {cell['captured_ms'][b]:.2f} ms", flush=True)
        cell["unfired_after_capture"] = report.unfired()
        images, img_masks, tokens, masks, noise = inputs[args.batches[0]]
        eager = model.sample_actions(images, img_masks, tokens, masks, noise=noise.clone(), num_steps=steps)
        captured = sampler(images, img_masks, tokens, masks, noise)
        cell["captured_vs_eager_rel_l2"] = ((captured.float() - eager.float()).norm() / eager.float().norm()).item()
        report.remove_hooks()
        results["cells"][preset] = cell
        del sampler
        torch.cuda.empty_cache()

    cells = results["cells"]
    print(f"\n{'preset':<12}" + "".join(f"{'b' + str(b) + ' ms':>10}{'/W4A4':>8}{'/base':>8}" for b in args.batches)
          + f"{'unfired':>9}{'relL2':>10}")
    for preset, cell in cells.items():
        line = f"{preset:<12}"
        for b in args.batches:
            ms = cell["captured_ms"][b]
            w4a4 = cells.get("W4A4", {}).get("captured_ms", {}).get(b)
            base = cells.get("BASELINE", {}).get("captured_ms", {}).get(b)
            cell.setdefault("ratio_to_w4a4", {})[b] = ms / w4a4 if w4a4 else None
            cell.setdefault("ratio_to_baseline", {})[b] = ms / base if base else None
            line += f"{ms:>10.2f}{(ms / w4a4 if w4a4 else float('nan')):>8.2f}{(ms / base if base else float('nan')):>8.2f}"
        print(line + f"{len(cell['unfired_after_capture']):>9}{cell['captured_vs_eager_rel_l2']:>10.1e}")
    with open(args.out, "w") as f:
        json.dump(results, f, indent=2)


if __name__ == "__main__":
    main()
