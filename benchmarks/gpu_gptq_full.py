"""GPTQ at full scale on the GPU (issue 31 item 2, "every model and scope"): pi0.5 at its released
widths, scope e2e (all 456 linears), through the path a GPTQ cell takes, phase by phase.

Model: lerobot 0.6.1 `PI05Pytorch` at full size, random weights (seed 0), as the cells build it
(`ModelSpec.build`: bf16, the SigLIP tower and projector float32); 2 cameras at 224 px, 200 prompt
tokens, 10 flow steps, batch 1, eager `sample_actions`.
Phases, each with its wall time, the peak GPU memory allocated (`torch.cuda.max_memory_allocated`)
and the peak of the process's anonymous host memory (RssAnon, sampled every 5 ms; a mapped file's
pages are not anonymous):
    calibrate   the rollout calibration's observer with the statistics the gptq method declares
                (`CalibrationSettings(...).observe`: absmax, clip quantile, sampled rows, X^T X of every
                layer's inputs) over `--chunks` chunks; the Hessians stay on the GPU
    save        `save_stats` (torch.save streams each Hessian from the GPU) to `--stats`
    quantize    `load_stats` (the file mapped, not read) and `quantize_` with `--method` (gptq, or
                hadamard_gptq: the rotations first, each Hessian mapped into its layer's rotated inputs)
                at `--preset`: one layer's float64 Hessian at a time, made on the GPU
Recorded: the statistics file's size, every layer's GPTQ output error on the calibration inputs
against RTN's at the same grid (`quant_report.gptq.error_vs_rtn_*`: mean and max of the ratio), each
component's `mean_rel_mse`, and the actions of a held-out chunk (other images, prompt and noise)
under RTN (with the same rotations for hadamard_gptq) and GPTQ against BASELINE's.

    python benchmarks/gpu_gptq_full.py --out benchmarks/results/gpu_gptq_full.json   # ~6 min, H100/H200
    python benchmarks/gpu_gptq_full.py --method hadamard_gptq --out benchmarks/results/gpu_hadamard_gptq_full.json
    python benchmarks/gpu_gptq_full.py --device cpu --smoke --out /tmp/g.json   # demo widths, CPU
"""

from __future__ import annotations

import argparse
import json
import re
import sys
import threading
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from gpu_fp8_real import rel_l2  # noqa: E402
from gpu_policy_inference import chunk_inputs, machine  # noqa: E402

from vlaquantbench.models import get_model_spec  # noqa: E402
from vlaquantbench.quant import QuantConfig, quantize_  # noqa: E402
from vlaquantbench.quant import calibration as calib  # noqa: E402

GIB = 2**30
# The GPTQ methods measured, each with the RTN method that rounds after the same transforms.
RTN_OF = {"gptq": "rtn", "hadamard_gptq": "hadamard"}


def rss_anon_gib() -> float:
    return int(re.search(r"RssAnon:\s+(\d+) kB", Path("/proc/self/status").read_text()).group(1)) / 2**20


class Phase:
    """Wall time, peak GPU memory allocated and peak RssAnon of the block it wraps, into `record`."""

    def __init__(self, record: dict, name: str, device: torch.device):
        self.record, self.name, self.cuda = record, name, device.type == "cuda"

    def __enter__(self):
        if self.cuda:
            torch.cuda.synchronize()
            torch.cuda.reset_peak_memory_stats()
        self.anon_before, self.peak, self.done = rss_anon_gib(), [rss_anon_gib()], threading.Event()
        self.sampler = threading.Thread(target=self._sample, daemon=True)
        self.sampler.start()
        self.start = time.perf_counter()
        return self

    def _sample(self):
        while not self.done.is_set():
            self.peak[0] = max(self.peak[0], rss_anon_gib())
            time.sleep(0.005)

    def __exit__(self, *exc):
        if self.cuda:
            torch.cuda.synchronize()
        wall = time.perf_counter() - self.start
        self.done.set()
        self.sampler.join()
        self.record[self.name] = {
            "wall_s": wall, "rss_anon_before_gib": self.anon_before, "rss_anon_peak_gib": self.peak[0],
            **({"gpu_peak_allocated_gib": torch.cuda.max_memory_allocated() / GIB,
                "gpu_allocated_after_gib": torch.cuda.memory_allocated() / GIB} if self.cuda else {})}
        print(self.name, {k: round(v, 3) for k, v in self.record[self.name].items()}, flush=True)


def actions(model, inputs, steps: int) -> torch.Tensor:
    images, img_masks, tokens, masks, noise = inputs
    with torch.no_grad():
        return model.sample_actions(images, img_masks, tokens, masks, noise=noise.clone(), num_steps=steps).float()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", required=True)
    parser.add_argument("--stats", default="/tmp/gptq_full_stats.pt", help="where the statistics file is written")
    parser.add_argument("--preset", default="W4A8")
    parser.add_argument("--method", choices=sorted(RTN_OF), default="gptq")
    parser.add_argument("--chunks", type=int, default=4, help="calibration chunks (batch 1)")
    parser.add_argument("--cameras", type=int, default=2)
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--smoke", action="store_true", help="demo widths, 2 chunks, 2 flow steps (checks the script runs)")
    args = parser.parse_args()
    variant = "full"
    if args.smoke:
        variant, args.chunks, args.steps = "demo", 2, 2
    device = torch.device(args.device)
    started = time.perf_counter()
    results = {"machine": machine() if device.type == "cuda" else {"device": "cpu"}, "variant": variant,
               "method": args.method, "preset": args.preset, "scope": "e2e", "chunks": args.chunks, "cameras": args.cameras, "steps": args.steps}
    phases = results["phases"] = {}
    write = lambda: Path(args.out).write_text(json.dumps(results, indent=1))  # noqa: E731

    spec = get_model_spec("pi05")
    calibration_inputs = [chunk_inputs(1, device, seed=100 + i, cameras=args.cameras) for i in range(args.chunks)]
    held_out = chunk_inputs(1, device, seed=0, cameras=args.cameras)
    with Phase(phases, "build", device):
        model = spec.build(variant=variant, device=device, seed=0).eval()
    baseline = actions(model, held_out, args.steps)

    config = QuantConfig.from_preset(args.preset, scope="e2e", method="gptq")
    selection = config.select(model, spec.components)
    layers = selection.flat()
    settings = calib.CalibrationSettings(alpha=None, components=tuple(selection.layers),
                                         **config.method.calibration_fields())
    results["calibration_settings"] = {"quantile": settings.quantile, "sample_rows": settings.sample_rows,
                                       "hessian": settings.hessian, "layers": len(layers)}
    with Phase(phases, "calibrate", device), settings.observe(layers) as observer:
        for inputs in calibration_inputs:
            actions(model, inputs, args.steps)
    stats = observer.stats("gptq-full", {"seed": 0, "chunks": args.chunks})
    results["hessian_gib"] = sum(s.hessian.numel() * s.hessian.element_size() for s in stats.layers.values()) / GIB
    results["rows_observed"] = {"min": min(s.rows for s in stats.layers.values()),
                                "max": max(s.rows for s in stats.layers.values())}
    with Phase(phases, "save", device):
        calib.save_stats(stats, args.stats)
    results["stats_file_gib"] = Path(args.stats).stat().st_size / GIB
    del stats, observer
    if device.type == "cuda":
        torch.cuda.empty_cache()
    write()

    with Phase(phases, "quantize", device):
        loaded = calib.load_stats(args.stats, "gptq-full")
        gptq_config = QuantConfig.from_preset(args.preset, scope="e2e", method=args.method, calibration=settings,
                                              stats=loaded)
        report = quantize_(model, gptq_config, gptq_config.select(model, spec.components))
    header = report.to_header()["quant_report"]
    results["gptq"] = header["gptq"]
    results["mean_rel_mse"] = {comp: header[comp]["mean_rel_mse"] for comp in selection.layers}
    results["quantized_layers"] = len(report.result.calibrated)
    gptq_actions = actions(model, held_out, args.steps)
    results["hooks_unfired_after_chunk"] = len(report.unfired())
    del model, report, loaded
    Path(args.stats).unlink()
    if device.type == "cuda":
        torch.cuda.empty_cache()
    write()

    rtn_model = spec.build(variant=variant, device=device, seed=0).eval()
    rtn_config = QuantConfig.from_preset(args.preset, scope="e2e", method=RTN_OF[args.method])
    quantize_(rtn_model, rtn_config, rtn_config.select(rtn_model, spec.components))
    rtn_actions = actions(rtn_model, held_out, args.steps)
    results["actions_rel_l2_vs_baseline"] = {"rtn": rel_l2(rtn_actions, baseline), "gptq": rel_l2(gptq_actions, baseline)}
    results["wall_s"] = time.perf_counter() - started
    print({k: v for k, v in results.items() if k not in ("phases", "machine")}, flush=True)
    write()
    print("wrote", args.out)


if __name__ == "__main__":
    main()
