"""Every GPU kernel of one pi0.5 chunk, BASELINE and then W4A4 (e2e, fused hooks), with counts and
summed times: where a quantized chunk's extra kernels and time come from.

The chunk runs the captured sampler's code without its graph (`static_sampling.sample_actions` under
the sampler's kernel choices, after one captured call has compiled everything), batch 1, full-size
random weights as in `gpu_policy_inference.py`, one model per preset (`quantized_model`).

    python benchmarks/gpu_kernel_diff.py --cameras 2 --out benchmarks/results/gpu_kernel_diff_cameras2.json
"""

from __future__ import annotations

import argparse
import json
import time

import torch

from gpu_policy_inference import chunk_inputs, kernel_profile, quantized_model, uncaptured_chunk  # sibling script
from vlaquantbench.models import get_model_spec
from vlaquantbench.models.pi05.fast import CapturedSampler


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cameras", type=int, default=2)
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    device = torch.device("cuda")
    spec = get_model_spec("pi05")
    inputs = chunk_inputs(1, device, cameras=args.cameras)
    out = {}
    for preset in ("BASELINE", "W4A4"):
        t0 = time.time()
        model, _ = quantized_model(spec, device, preset)
        sampler = CapturedSampler(model, num_steps=10)
        sampler(*inputs)
        chunk = uncaptured_chunk(model, sampler, inputs)
        with sampler._kernel_choices():
            chunk()
            out[preset] = kernel_profile(chunk, top_n=400)
        print(preset, out[preset]["kernels"], out[preset]["kernel_time_ms"], round(time.time() - t0, 1), flush=True)
        with open(args.out, "w") as f:
            json.dump(out, f, indent=1)
        del model, sampler, chunk
        torch.cuda.empty_cache()


if __name__ == "__main__":
    main()
