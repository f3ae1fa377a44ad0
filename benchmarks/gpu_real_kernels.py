"""Real quantization kernels vs BF16 (paper `app:kernel`): peak allocated GiB and full-inference time.

Backbones (random weights, bf16, CUDA, batch 1):
* OpenVLA-OFT's LLM: a LLaMA-2-7B `LlamaModel` (transformers config: 4096 wide, 32 layers, 11008
  MLP), one parallel forward over 600 tokens (two 256-patch vision streams, prompt and the action
  chunk's placeholder tokens), the OFT way of decoding a chunk; all 224 linears quantized.
* pi0.5 (`PI05Pytorch`, lerobot 0.6.1): a whole chunk through the captured sampler
  (`vlaquantbench.models.pi05.fast`), LLM scope (126 linears) quantized.

Per method, in its own process, a fresh model is built, quantized through `quantize_` (methods of
`vlaquantbench.quant.kernels`), the CUDA allocator's peak is reset, and each form of the forward
runs 3 warm-up calls (discarded) then `--repeats` timed calls, CUDA-synchronized, all under
`torch.no_grad()` (inference: no autograd graph, no saved activations); the median is reported
with the relative L2 deviation of the output from BF16's output in the same form. LLaMA forms,
applied identically to every method:

* eager:          the model as `quantize_` leaves it;
* graph:          the eager forward captured as one CUDA graph (launch gaps removed);
* compiled_graph: each decoder layer compiled by inductor (`nn.Module.compile`; the 32 identical
                  layers share one compiled graph, so the elementwise work between the matrix
                  products -- norms, rotary, residuals, per-token activation quantization -- is
                  fused once), run with inductor's own CUDA graphs ("reduce-overhead"; on the
                  CPU: `compiled`, without graphs). The counting
                  hooks are removed first: they proved in the eager run that every kernel layer
                  fired, change nothing, and their Python call counters would make dynamo
                  recompile per layer. `compile_s` is the first compiled call, inductor cache
                  cold (a fresh cache folder per run).

A method whose kernels cannot be compiled or captured (bitsandbytes) reports the error and keeps
its other forms. Headline per method: `full_inference_ms` = its fastest form, `speedup_vs_bf16`
against BF16's fastest form; per-form ratios in `speedup_vs_bf16_by_form`.

    python benchmarks/gpu_real_kernels.py --out benchmarks/results/gpu_real_kernels.json --backbones llama2_7b
    python benchmarks/gpu_real_kernels.py --out benchmarks/results/gpu_real_kernels.json --backbones pi05
    python benchmarks/gpu_real_kernels.py --out /tmp/smoke.json --device cpu --tiny   # CPU smoke run

`--out` keeps the rows of backbones and methods not run this time (so a run can be split).
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch
from gpu_policy_inference import chunk_inputs, kernel_profile  # sibling script
from torch import nn
from torch._dynamo.utils import counters

from vlaquantbench.models.pi05.fast.captured import capture_graph
from vlaquantbench.models.registry import Component
from vlaquantbench.quant import QuantConfig, quantize_
from vlaquantbench.quant.calibration import observe
from vlaquantbench.quant.kernels.packed import FP8, quantize_per_token

METHODS = {  # method -> preset it implements
    "bf16": None, "nf4": "W4", "int8": "W8", "int4wo": "W4", "smoothquant": "W8A8", "fp8": "W8A8", "fp8_tensor": "W8A8",
    "fp8_static": "W8A8",
}
CALIBRATED = {"fp8_static"}  # methods whose activation scales come from a calibration forward
CPU_METHODS = ("bf16", "smoothquant", "fp8_tensor", "fp8_static")  # the kernels PyTorch also has on the CPU
FORMS = ("eager", "graph", "compiled", "compiled_graph")  # compiled: inductor without the CUDA graph
GIB = 2**30


@dataclass
class Backbone:
    model: nn.Module
    components: dict
    run: Callable[[], torch.Tensor]
    blocks: list[nn.Module] | None = None  # compiled one by one for the compiled forms; None: no such forms
    capture: bool = True  # False: `run` captures its own graph (pi05's sampler)
    calibrate: Callable[[], object] | None = None  # an eager forward for calibration hooks (default: run)


def llama7b(device: torch.device, tiny: bool) -> Backbone:
    from transformers import LlamaConfig, LlamaModel

    if tiny:  # the same architecture at a width that runs on a CPU in seconds
        dims = {"hidden_size": 256, "intermediate_size": 512, "num_hidden_layers": 2, "num_attention_heads": 4,
                "vocab_size": 100}
    else:
        dims = {"hidden_size": 4096, "intermediate_size": 11008, "num_hidden_layers": 32, "num_attention_heads": 32,
                "vocab_size": 32000}
    config = LlamaConfig(**dims, num_key_value_heads=dims["num_attention_heads"], max_position_embeddings=4096)
    config._attn_implementation = "sdpa"
    previous = torch.get_default_dtype()
    torch.set_default_dtype(torch.bfloat16)
    torch.manual_seed(0)  # the same random weights for every method
    try:
        with device:
            model = LlamaModel(config).eval()
    finally:
        torch.set_default_dtype(previous)
    components = {"llm": Component(roots=("layers",))}
    tokens = 64 if tiny else 600
    inputs = torch.randn(1, tokens, config.hidden_size, generator=torch.Generator().manual_seed(0))
    inputs = inputs.to(device, torch.bfloat16)

    def run():  # one parallel forward: no KV cache (never read here, and filling it copies every K and V)
        return model(inputs_embeds=inputs, use_cache=False).last_hidden_state

    return Backbone(model, components, run, blocks=list(model.layers))


def pi05(device: torch.device, tiny: bool) -> Backbone:
    from vlaquantbench.models.pi05.fast import CapturedSampler
    from vlaquantbench.models import get_model_spec

    spec = get_model_spec("pi05")
    model = spec.build(variant="full", device="cuda", seed=0).eval()
    images, img_masks, tokens, masks, noise = chunk_inputs(1, torch.device("cuda"))
    holder = {}

    def run():  # the sampler is made on first call, after quantization replaced the layers
        if "sampler" not in holder:
            holder["sampler"] = CapturedSampler(model, num_steps=10)
        return holder["sampler"](images, img_masks, tokens, masks, noise)

    def calibrate():  # lerobot's eager sampler: the observer's hooks copy to the host, no graph capture
        return model.sample_actions(images, img_masks, tokens, masks, noise=noise, num_steps=10)

    return Backbone(model, spec.components, run, capture=False, calibrate=calibrate)


BACKBONES = {"llama2_7b": llama7b, "pi05": pi05}


def graphed(fn):
    """`fn` captured as one CUDA graph; returns a replaying callable."""
    graph, out = capture_graph(fn)

    def replay():
        graph.replay()
        return out

    return replay


def median_ms(fn, repeats: int, sync) -> float:
    """Median wall time of `repeats` calls after 3 discarded warm-ups, synchronized after each."""
    for _ in range(3):
        fn()
    sync()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        sync()
        times.append(time.perf_counter() - start)
    return 1e3 * statistics.median(times)


def rel_l2(out: torch.Tensor, reference: torch.Tensor) -> float:
    return ((out - reference).norm() / reference.norm()).item()


def measure(backbone: Backbone, method: str, repeats: int, references: dict | None, compile_blocks: bool) -> tuple:
    """Quantize, then time every form of the forward; returns (entry, outputs by form)."""
    cuda = next(backbone.model.parameters()).is_cuda
    sync = torch.cuda.synchronize if cuda else (lambda: None)
    entry = {"method": method, "date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "peak_gib_by_form": {}}
    outputs = {}

    def record(form: str, fn, profile: bool = False) -> None:
        if cuda:
            gc.collect()
            torch.cuda.empty_cache()
            torch.cuda.reset_peak_memory_stats()
        entry[f"{form}_ms"] = median_ms(fn, repeats, sync)
        outputs[form] = fn().detach().to(torch.float32, copy=True)  # a graph's output buffer is rewritten
        entry["peak_gib_by_form"][form] = torch.cuda.max_memory_allocated() / GIB if cuda else None
        if profile and cuda:
            entry[f"{form}_profile"] = kernel_profile(fn, top_n=3)

    try:
        report = None
        if METHODS[method] is not None:
            stats = calibrate(backbone) if method in CALIBRATED else None
            cfg = QuantConfig.from_preset(METHODS[method], scope="llm", method=method, stats=stats)
            report = quantize_(backbone.model, cfg, cfg.select(backbone.model, backbone.components))
            entry.update(format=report.result.format, layers=report.components)
        else:
            entry.update(format="bf16 (released precision)")
        # Inference: without no_grad every forward records autograd (weights and norm scales are
        # parameters) and keeps its saved activations alive -- in a captured graph, for good.
        with torch.no_grad():
            record("eager", backbone.run, profile=not backbone.capture)
            if report is not None:
                entry["unfired"] = len(report.unfired())
            if cuda and backbone.capture:  # launch gaps removed for every method alike
                try:
                    record("graph", graphed(backbone.run), profile=True)
                except Exception as err:  # noqa: BLE001  (e.g. a kernel library that synchronizes with the host)
                    entry["graph_error"] = f"{type(err).__name__}: {err}"[:300]
                    sync()
            if compile_blocks and backbone.blocks is not None:
                try:
                    compile_forms(backbone, report, entry, record, sync, cuda)
                except Exception as err:  # noqa: BLE001  (a kernel library dynamo cannot trace)
                    entry["compile_error"] = f"{type(err).__name__}: {err}"[:500]
                    traceback.print_exc()
                    sync()
        times = {form: entry[f"{form}_ms"] for form in FORMS if f"{form}_ms" in entry}
        best = min(times, key=times.get)
        peaks = [p for p in entry["peak_gib_by_form"].values() if p is not None]
        entry.update(full_inference_form=best, full_inference_ms=times[best], peak_allocated_gib=max(peaks, default=None))
        compiled = "compiled_graph" if "compiled_graph" in outputs else "compiled"
        if compiled in outputs:  # the fused activation quantization computes what the eager kernels do
            entry["rel_l2_compiled_vs_eager"] = rel_l2(outputs[compiled], outputs["eager"])
        if references is not None:
            entry["rel_l2_vs_bf16_by_form"] = {f: rel_l2(outputs[f], references[f]) for f in outputs if f in references}
            entry["rel_l2_vs_bf16"] = entry["rel_l2_vs_bf16_by_form"].get(best)
    except Exception as err:  # noqa: BLE001  (one failing kernel must not hide the others' numbers)
        entry["error"] = f"{type(err).__name__}: {err}"[:500]
        traceback.print_exc()
    return entry, outputs


def fused_quantize_check(device: torch.device) -> dict:
    """Per-token activation quantization of one LLaMA-sized input (bf16, rows of mixed magnitude):
    the eager path (the Triton kernel on CUDA) against the torch expression that inductor fuses
    under `torch.compile`: fraction of equal quantized values and the largest relative scale difference."""
    g = torch.Generator().manual_seed(0)
    x = (torch.randn(600, 4096, generator=g) * torch.rand(600, 1, generator=g) * 5).to(device, torch.bfloat16)
    fused = torch.compile(quantize_per_token)
    out = {}
    for dtype in (torch.int8, FP8):
        values, scales = quantize_per_token(x, dtype)
        fused_values, fused_scales = fused(x, dtype)
        out[str(dtype).removeprefix("torch.")] = {
            "values_equal": (values.float() == fused_values.float()).float().mean().item(),
            "scale_max_rel_diff": ((scales - fused_scales).abs() / scales).max().item(),
        }
    return out


def calibrate(backbone: Backbone):
    """Input absmax of every linear layer over one unquantized forward on the benchmark's own
    input (the static scales' best case: nothing saturates)."""
    layers = {n: m for n, m in backbone.model.named_modules() if isinstance(m, nn.Linear)}
    with observe(layers, quantile=None) as observer, torch.no_grad():
        (backbone.calibrate or backbone.run)()
    return observer.stats("benchmark-input", {"input": "the benchmark's own forward"})


def compile_forms(backbone: Backbone, report, entry: dict, record, sync, cuda: bool) -> None:
    """Each block compiled by inductor (one shared graph for identical blocks), timed as is and
    captured as one CUDA graph."""
    if report is not None:  # they fired in the eager run and change nothing; dynamo would guard on their counters
        report.remove_hooks()
    # A recompilation per block would hit dynamo's limit and silently leave the rest eager: fail instead.
    torch._dynamo.config.fail_on_recompile_limit_hit = True
    # On CUDA, inductor's own CUDA graphs ("reduce-overhead"): capturing the compiled blocks by hand
    # (`graphed`) failed on the H100 with cudaErrorStreamCaptureInvalidated.
    graphs = cuda and backbone.capture
    for block in backbone.blocks:
        block.compile(mode="reduce-overhead" if graphs else None)

    def run():  # one forward = one step of inductor's graphs (each block's output feeds the next)
        if graphs:
            torch.compiler.cudagraph_mark_step_begin()
        return backbone.run()

    start = time.perf_counter()
    run()
    sync()
    entry["compile_s"] = time.perf_counter() - start
    entry["compiled_graphs"] = counters["stats"]["unique_graphs"]  # 1: no recompilation per layer
    entry["graph_breaks"] = sum(counters["graph_break"].values())
    record("compiled_graph" if graphs else "compiled", run, profile=graphs)


def run_one(backbone: str, method: str, args, reference_path: Path) -> dict:
    """One (backbone, method) measurement, in its own process: peak memory then belongs to that
    method alone, and a kernel library that breaks CUDA graph capture cannot poison the others."""
    references = torch.load(reference_path) if method != "bf16" else None
    built = BACKBONES[backbone](torch.device(args.device), args.tiny)
    entry, outputs = measure(built, method, args.repeats, references, compile_blocks=not args.no_compile)
    if method == "bf16" and "error" not in entry:
        torch.save(outputs, reference_path)
        entry["quantize_fused_vs_eager"] = fused_quantize_check(torch.device(args.device))
    return entry


def add_ratios(rows: list[dict]) -> None:
    """Speed-ups and memory against the BF16 row: headline (fastest form each) and form by form."""
    base = next((r for r in rows if r["method"] == "bf16" and "full_inference_ms" in r), None)
    for r in rows:
        if base is None or "full_inference_ms" not in r:
            continue
        r["speedup_vs_bf16"] = base["full_inference_ms"] / r["full_inference_ms"]
        r["speedup_vs_bf16_by_form"] = {f: base[f"{f}_ms"] / r[f"{f}_ms"] for f in FORMS
                                        if f"{f}_ms" in r and f"{f}_ms" in base}
        if r["peak_allocated_gib"] is not None:
            r["memory_vs_bf16"] = r["peak_allocated_gib"] / base["peak_allocated_gib"]


def child_command(args, out: Path, backbone: str, method: str) -> list[str]:
    command = [sys.executable, __file__, "--out", str(out), "--repeats", str(args.repeats), "--device", args.device,
               "--one", backbone, method]
    return command + ["--tiny"] * args.tiny + ["--no-compile"] * args.no_compile


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", required=True, help="JSON file; rows of backbones/methods not run now are kept")
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--methods", nargs="+", choices=list(METHODS), help="default: all (on --device cpu: the CPU ones)")
    parser.add_argument("--backbones", nargs="+", choices=list(BACKBONES), help="default: all (--tiny: llama2_7b)")
    parser.add_argument("--device", default="cuda", choices=["cuda", "cpu"])
    parser.add_argument("--tiny", action="store_true", help="2 layers, width 256, 64 tokens (smoke runs)")
    parser.add_argument("--no-compile", action="store_true", help="skip the compiled forms")
    parser.add_argument("--one", nargs=2, metavar=("BACKBONE", "METHOD"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    args.backbones = args.backbones or (["llama2_7b"] if args.tiny or args.device == "cpu" else list(BACKBONES))
    args.methods = args.methods or list(CPU_METHODS if args.device == "cpu" else METHODS)
    if "pi05" in args.backbones and (args.tiny or args.device == "cpu"):
        parser.error("--backbones pi05 runs at full size on CUDA only (drop --tiny / --device cpu)")
    if args.device == "cpu" and not args.tiny:
        parser.error("--device cpu needs --tiny (the full-size backbones are GPU workloads)")
    if args.device == "cpu" and set(args.methods) - set(CPU_METHODS):
        parser.error(f"--methods {sorted(set(args.methods) - set(CPU_METHODS))} need CUDA; on the CPU: {CPU_METHODS}")
    if args.device == "cuda" and not torch.cuda.is_available():
        parser.error("--device cuda: no CUDA device here (use --device cpu --tiny for a smoke run)")
    return args


def main() -> None:
    args = parse_args()
    if args.one:  # child process: write one entry as JSON to --out
        entry = run_one(*args.one, args, Path(args.out).with_suffix(".reference.pt"))
        Path(args.out).write_text(json.dumps(entry))
        return
    out_path = Path(args.out)
    results = json.loads(out_path.read_text()) if out_path.exists() else {"backbones": {}}
    machine = {"gpu": torch.cuda.get_device_name() if args.device == "cuda" else "cpu", "torch": torch.__version__,
               "date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "tiny": args.tiny}
    try:
        import bitsandbytes

        machine["bitsandbytes"] = bitsandbytes.__version__
    except ImportError:
        pass
    results["machine"] = machine
    with tempfile.TemporaryDirectory() as tmp:
        # A fresh inductor cache per run: `compile_s` is a cold compile for every method.
        env = {**os.environ, "TORCHINDUCTOR_CACHE_DIR": str(Path(tmp) / "inductor")}
        for name in args.backbones:
            results.setdefault("machine_by_backbone", {})[name] = machine
            rows = {r["method"]: r for r in results["backbones"].get(name, [])}
            for method in ["bf16", *(m for m in args.methods if m != "bf16")]:  # bf16 first: the reference
                child_out = Path(tmp) / f"{name}.json"
                child_out.unlink(missing_ok=True)
                proc = subprocess.run(child_command(args, child_out, name, method), capture_output=True, text=True, env=env,
                                      check=False)
                if child_out.exists():
                    entry = json.loads(child_out.read_text())
                else:
                    entry = {"method": method, "error": f"process exited {proc.returncode}: {proc.stderr[-400:]}"}
                rows[method] = entry
                shown = {k: v for k, v in entry.items() if k not in ("layers", "format") and not k.endswith("profile")}
                print(f"[{name}] {method}: {json.dumps(shown)[:600]}", flush=True)
            results["backbones"][name] = list(rows.values())
            add_ratios(results["backbones"][name])
            out_path.write_text(json.dumps(results, indent=1))
    print_table(results)


def print_table(results: dict) -> None:
    def cell(value, fmt=">9.2f"):
        return format(value, fmt) if value is not None else f"{'-':>9}"

    print(f"\n{'backbone':<11}{'method':<13}{'GiB':>7}{'eager':>9}{'graph':>9}{'compiled':>9}{'cmp+grph':>9}"
          f"{'compile':>9}{'speedup':>9}{'rel err':>9}   (ms; compile s; speedup: fastest form vs BF16's)")
    for name, rows in results["backbones"].items():
        for r in rows:
            if "full_inference_ms" not in r:
                print(f"{name:<11}{r['method']:<13}  failed: {r['error'][:80]}")
                continue
            print(f"{name:<11}{r['method']:<13}{cell(r['peak_allocated_gib'], '>7.2f')}{cell(r.get('eager_ms'))}"
                  f"{cell(r.get('graph_ms'))}{cell(r.get('compiled_ms'))}{cell(r.get('compiled_graph_ms'))}"
                  f"{cell(r.get('compile_s'), '>9.1f')}{cell(r.get('speedup_vs_bf16'))}"
                  f"{cell(r.get('rel_l2_vs_bf16'), '>9.3f')}")
            for key in ("graph_error", "compile_error"):
                if key in r:
                    print(f"{'':<24}{key}: {r[key][:100]}")


if __name__ == "__main__":
    main()
