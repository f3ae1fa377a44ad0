"""Real-kernel linears on the GPU: torchao's `quantize_` configs next to the hand-written modules of
`quant.kernels`, per method and shape, eager and under `torch.compile`, side by side in one process.

    int8        Int8DynamicLinear               vs Int8DynamicActivationInt8WeightConfig()
    fp8_row     Fp8DynamicLinear                vs Float8DynamicActivationFloat8WeightConfig(PerRow())
    fp8_tensor  Fp8DynamicLinear(tensorwise)    vs Float8DynamicActivationFloat8WeightConfig(PerTensor())
    fp8_static  Fp8StaticLinear(absmax)         vs Float8StaticActivationFloat8WeightConfig(act_quant_scale=absmax/448)
    int4wo      Int4WeightOnlyLinear(group 128) vs Int4WeightOnlyConfig(128, int4_packing_format="tile_packed_to_4d")

bf16 weights and inputs. Reported per row: median ms per call of each (CUDA-synchronized), the ratio
torchao / hand-written, and both outputs' relative L2 error against the bf16 product. This decides
issue 14's "use torchao's kernels unless a benchmark shows a reason to keep yours" for the GPU
(the CPU int8 comparison is `bench_torchao_int8_cpu.py`).

    python benchmarks/gpu_torchao_kernels.py --out benchmarks/results/gpu_torchao_kernels.json
"""

from __future__ import annotations

import argparse
import copy
import json
import statistics
import time

import torch
import torchao
from gpu_policy_inference import time_chunks
from torchao.quantization import (
    Float8DynamicActivationFloat8WeightConfig,
    Int4WeightOnlyConfig,
    Int8DynamicActivationInt8WeightConfig,
    PerRow,
    PerTensor,
)
from torchao.quantization import quantize_ as ao_quantize

from vlaquantbench.quant import kernels

# (tokens, in, out): LLaMA-2-7B projections at one OpenVLA-OFT chunk; pi0.5 expert (batch 1) and prefix (batch 8)
SHAPES = [(64, 4096, 4096), (64, 4096, 11008), (50, 1024, 4096), (1936, 2048, 16384)]


def _static_config(absmax):
    from torchao.prototype.quantization.quant_api import Float8StaticActivationFloat8WeightConfig

    return Float8StaticActivationFloat8WeightConfig(act_quant_scale=(absmax.amax() / kernels.FP8_MAX).float().reshape(1, 1),
                                                    granularity=PerTensor())


METHODS = {
    "int8": (lambda lin, amax: kernels.Int8DynamicLinear(lin), lambda amax: Int8DynamicActivationInt8WeightConfig()),
    "fp8_row": (lambda lin, amax: kernels.Fp8DynamicLinear(lin),
                lambda amax: Float8DynamicActivationFloat8WeightConfig(granularity=PerRow())),
    "fp8_tensor": (lambda lin, amax: kernels.Fp8DynamicLinear(lin, tensorwise=True),
                   lambda amax: Float8DynamicActivationFloat8WeightConfig(granularity=PerTensor())),
    "fp8_static": (lambda lin, amax: kernels.Fp8StaticLinear(lin, amax), _static_config),
    "int4wo": (lambda lin, amax: kernels.Int4WeightOnlyLinear(lin, 128),
               lambda amax: Int4WeightOnlyConfig(group_size=128, int4_packing_format="tile_packed_to_4d")),
}


def _rel(a, b) -> float:
    return ((a.float() - b.float()).norm() / b.float().norm()).item()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", required=True)
    parser.add_argument("--repeats", type=int, default=50)
    parser.add_argument("--methods", nargs="+", default=list(METHODS))
    parser.add_argument("--shapes", nargs="+", default=["x".join(map(str, s)) for s in SHAPES],
                        help="tokens x in x out, e.g. 64x4096x11008 (rows are written as they finish)")
    args = parser.parse_args()
    shapes = [tuple(int(v) for v in shape.split("x")) for shape in args.shapes]
    device = torch.device("cuda")
    torch.manual_seed(0)
    rows = []
    out = {"device": torch.cuda.get_device_name(device), "torch": torch.__version__, "torchao": torchao.__version__,
           "date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "rows": rows}
    with torch.no_grad():
        for tokens, fan_in, fan_out in shapes:
            linear = torch.nn.Linear(fan_in, fan_out, bias=False).to(device, torch.bfloat16)
            x = torch.randn(tokens, fan_in, device=device, dtype=torch.bfloat16)
            ref = linear(x)
            amax = x.abs().amax(dim=0).float()
            for method in args.methods:
                make_hand, make_config = METHODS[method]
                row = {"method": method, "shape": [tokens, fan_in, fan_out]}
                try:
                    hand = make_hand(copy.deepcopy(linear), amax)
                    ao = torch.nn.Sequential(copy.deepcopy(linear))
                    ao_quantize(ao, make_config(amax))
                    forms = {"hand": hand, "torchao": ao}
                    forms.update({f"{k}_compiled": torch.compile(m) for k, m in list(forms.items())})
                    for name, module in forms.items():
                        row[f"{name}_ms"] = 1e3 * statistics.median(
                            time_chunks(lambda module=module: module(x), warmup=5, repeats=args.repeats))
                        row[f"{name}_rel_err"] = _rel(module(x), ref)
                    for form in ("", "_compiled"):
                        row[f"torchao_over_hand{form}"] = row[f"torchao{form}_ms"] / row[f"hand{form}_ms"]
                except Exception as err:  # noqa: BLE001 - recorded: a config this GPU / version cannot run
                    row["error"] = f"{type(err).__name__}: {str(err)[:300]}"
                rows.append(row)
                print(json.dumps(row), flush=True)
                with open(args.out, "w") as f:  # a run cut short keeps its finished rows
                    json.dump(out, f, indent=2)
                torch._dynamo.reset()
    print(f"\n{'method':<11}{'shape':>20}{'hand ms':>9}{'ao ms':>9}{'ao/hand':>9}{'compiled':>10}")
    for r in rows:
        if "error" in r:
            print(f"{r['method']:<11}{'x'.join(map(str, r['shape'])):>20}  {r['error'][:60]}")
            continue
        print(f"{r['method']:<11}{'x'.join(map(str, r['shape'])):>20}{r['hand_ms']:>9.3f}{r['torchao_ms']:>9.3f}"
              f"{r['torchao_over_hand']:>9.2f}{r['torchao_over_hand_compiled']:>10.2f}")
    with open(args.out, "w") as f:
        json.dump(out, f, indent=2)


if __name__ == "__main__":
    main()
