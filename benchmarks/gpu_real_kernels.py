"""Real quantization kernels vs BF16 (paper `app:kernel`): peak allocated GiB and full-inference time.

Backbones (random weights, bf16, CUDA, batch 1):
* OpenVLA-OFT's LLM: a LLaMA-2-7B `LlamaModel` (transformers config: 4096 wide, 32 layers, 11008
  MLP), one parallel forward over 600 tokens (two 256-patch vision streams, prompt and the action
  chunk's placeholder tokens), the OFT way of decoding a chunk; all 224 linears quantized.
* pi0.5 (`PI05Pytorch`, lerobot 0.6.1): a whole chunk through the captured sampler
  (`vlaquantbench.accel`), LLM scope (126 linears) quantized.

Per method, in its own process, a fresh model is built, quantized through `quantize_` (methods of
`vlaquantbench.quant.kernels`), the CUDA allocator's peak is reset, and inference runs 3 warm-up
calls (discarded) then `--repeats` timed calls, CUDA-synchronized; the median is reported along
with the relative L2 deviation of the output from BF16 on the same input.

    python benchmarks/gpu_real_kernels.py --out benchmarks/results/gpu_real_kernels.json
"""

from __future__ import annotations

import argparse
import gc
import json
import statistics
import subprocess
import sys
import tempfile
import time
import traceback
from pathlib import Path

import torch

import vlaquantbench.quant.kernels  # noqa: F401  (registers the real-kernel methods)
from gpu_policy_inference import chunk_inputs, kernel_profile, time_chunks  # this folder's sibling script
from vlaquantbench.accel.captured import capture_graph
from vlaquantbench.models.registry import Component
from vlaquantbench.quant import QuantConfig, quantize_

METHODS = {  # method -> preset it implements
    "bf16": None, "nf4": "W4", "int8": "W8", "int4wo": "W4", "smoothquant": "W8A8", "fp8": "W8A8", "fp8_tensor": "W8A8",
}
GIB = 2**30


def llama7b():
    from transformers import LlamaConfig, LlamaModel

    config = LlamaConfig(hidden_size=4096, intermediate_size=11008, num_hidden_layers=32, num_attention_heads=32,
                         num_key_value_heads=32, vocab_size=32000, max_position_embeddings=4096)
    config._attn_implementation = "sdpa"
    previous = torch.get_default_dtype()
    torch.set_default_dtype(torch.bfloat16)
    torch.manual_seed(0)  # the same random weights for every method
    try:
        with torch.device("cuda"):
            model = LlamaModel(config).eval()
    finally:
        torch.set_default_dtype(previous)
    components = {"llm": Component(roots=("layers",))}
    inputs = torch.randn(1, 600, 4096, generator=torch.Generator().manual_seed(0)).to("cuda", torch.bfloat16)
    return model, components, lambda: model(inputs_embeds=inputs).last_hidden_state


def pi05():
    from vlaquantbench.accel import CapturedSampler
    from vlaquantbench.models import get_model_spec

    spec = get_model_spec("pi05")
    model = spec.build(variant="full", device="cuda", seed=0).eval()
    images, img_masks, tokens, masks, noise = chunk_inputs(1, torch.device("cuda"))
    holder = {}

    def run():  # the sampler is made on first call, after quantization replaced the layers
        if "sampler" not in holder:
            holder["sampler"] = CapturedSampler(model, num_steps=10)
        return holder["sampler"](images, img_masks, tokens, masks, noise)

    return model, spec.components, run


def graphed(fn):
    """`fn` captured as one CUDA graph; returns a replaying callable."""
    graph, out = capture_graph(fn)

    def replay():
        graph.replay()
        return out

    return replay


def measure(backbone, method: str, repeats: int, reference, capture: bool) -> dict:
    model, components, run = backbone()
    entry = {"method": method}
    try:
        if METHODS[method] is not None:
            cfg = QuantConfig.from_preset(METHODS[method], scope="llm", method=method)
            report = quantize_(model, cfg, components=components)
            entry.update(format=report.result.format, layers=report.components)
        else:
            entry.update(format="bf16 (released precision)")
        gc.collect()
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats()
        times = time_chunks(run, warmup=3, repeats=repeats)
        entry["eager_ms"] = 1e3 * statistics.median(times)
        if capture:  # the same forward as one CUDA graph: launch gaps removed for every method alike
            try:
                run = graphed(run)
                entry["graph_ms"] = 1e3 * statistics.median(time_chunks(run, warmup=3, repeats=repeats))
            except Exception as err:  # e.g. a kernel library that synchronizes with the host
                entry["graph_error"] = f"{type(err).__name__}: {err}"[:300]
                torch.cuda.synchronize()
        entry["profile"] = kernel_profile(run, top_n=3)
        out = run().float()
        entry.update(
            full_inference_ms=entry.get("graph_ms", entry["eager_ms"]),
            peak_allocated_gib=torch.cuda.max_memory_allocated() / GIB,
            rel_l2_vs_bf16=None if reference is None else ((out - reference).norm() / reference.norm()).item(),
        )
        if METHODS[method] is not None:
            entry["unfired"] = len(report.unfired())
        result = entry, (out if reference is None else None)
    except Exception as err:  # one failing kernel must not hide the others' numbers
        entry["error"] = f"{type(err).__name__}: {err}"[:500]
        traceback.print_exc()
        result = entry, None
    del model, run
    gc.collect()
    torch.cuda.empty_cache()
    return result


def run_one(backbone: str, method: str, repeats: int, reference_path: Path) -> dict:
    """One (backbone, method) measurement, in its own process: peak memory then belongs to that
    method alone, and a kernel library that breaks CUDA graph capture cannot poison the others."""
    reference = torch.load(reference_path) if method != "bf16" else None
    entry, out = measure(BACKBONES[backbone], method, repeats, reference, capture=backbone != "pi05")
    if method == "bf16" and out is not None:
        torch.save(out, reference_path)
    return entry


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", required=True)
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--methods", nargs="+", default=list(METHODS))
    parser.add_argument("--backbones", nargs="+", default=list(BACKBONES))
    parser.add_argument("--one", nargs=2, metavar=("BACKBONE", "METHOD"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one:  # child process: write one entry as JSON to --out
        entry = run_one(*args.one, args.repeats, Path(args.out).with_suffix(".reference.pt"))
        Path(args.out).write_text(json.dumps(entry))
        return
    results = {"machine": {"gpu": torch.cuda.get_device_name(), "torch": torch.__version__,
                           "date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}, "backbones": {}}
    try:
        import bitsandbytes

        results["machine"]["bitsandbytes"] = bitsandbytes.__version__
    except ImportError:
        pass
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.backbones:
            rows = []
            for method in ["bf16", *(m for m in args.methods if m != "bf16")]:
                child_out = Path(tmp) / f"{name}.json"
                child_out.unlink(missing_ok=True)
                proc = subprocess.run([sys.executable, __file__, "--out", str(child_out), "--repeats", str(args.repeats),
                                       "--one", name, method], capture_output=True, text=True)
                if child_out.exists():
                    entry = json.loads(child_out.read_text())
                else:
                    entry = {"method": method, "error": f"process exited {proc.returncode}: {proc.stderr[-400:]}"}
                rows.append(entry)
                print(f"[{name}] {method}: {json.dumps({k: v for k, v in entry.items() if k != 'layers'})[:400]}",
                      flush=True)
            base = next((r for r in rows if r["method"] == "bf16" and "full_inference_ms" in r), None)
            for r in rows:
                if base and "full_inference_ms" in r:
                    r["speedup_vs_bf16"] = base["full_inference_ms"] / r["full_inference_ms"]
                    r["eager_speedup_vs_bf16"] = base["eager_ms"] / r["eager_ms"]
                    r["memory_vs_bf16"] = r["peak_allocated_gib"] / base["peak_allocated_gib"]
            results["backbones"][name] = rows
            with open(args.out, "w") as f:
                json.dump(results, f, indent=1)
    print(f"\n{'backbone':<11}{'method':<13}{'GiB':>7}{'eager ms':>9}{'ms':>9}{'speedup':>9}{'rel err':>9}")
    for name, rows in results["backbones"].items():
        for r in rows:
            if "full_inference_ms" in r:
                rel = r["rel_l2_vs_bf16"]
                print(f"{name:<11}{r['method']:<13}{r['peak_allocated_gib']:>7.2f}{r['eager_ms']:>9.2f}"
                      f"{r['full_inference_ms']:>9.2f}{r.get('speedup_vs_bf16', float('nan')):>9.2f}"
                      f"{rel if rel is not None else 0:>9.3f}")
            else:
                print(f"{name:<11}{r['method']:<13}  failed: {r['error'][:80]}")


BACKBONES = {"llama2_7b": llama7b, "pi05": pi05}


if __name__ == "__main__":
    main()
