"""Every GPU kernel of one pi0.5 chunk, BASELINE and then W4A4 (e2e, fused hooks), with counts and
summed times: where a quantized chunk's extra kernels and time come from.

The chunk runs the captured sampler's code without its graph (`static_sampling.sample_actions` under
the sampler's kernel choices, after one captured call has compiled everything), batch 1, full-size
random weights as in `gpu_policy_inference.py`. One model, quantized in place after the BASELINE
profile.

    python benchmarks/gpu_kernel_diff.py --cameras 2 --out benchmarks/results/gpu_kernel_diff_cameras2.json
"""

from __future__ import annotations

import argparse
import json
import time

import torch

from gpu_policy_inference import chunk_inputs, kernel_profile  # sibling script
from vlaquantbench.models import get_model_spec
from vlaquantbench.models.pi05.fast import CapturedSampler
from vlaquantbench.models.pi05.fast import static_sampling
from vlaquantbench.quant import QuantConfig, quantize_
from vlaquantbench.quant.fused_kernel import fuse_activation_hooks


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cameras", type=int, default=2)
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    device = torch.device("cuda")
    spec = get_model_spec("pi05")
    model = spec.build(variant="full", device=device, seed=0).eval()
    images, img_masks, tokens, masks, noise = chunk_inputs(1, device, cameras=args.cameras)
    out = {}
    for preset in ("BASELINE", "W4A4"):
        t0 = time.time()
        config = QuantConfig.from_preset(preset, scope="e2e")
        report = quantize_(model, config, config.select(model, spec.components))
        fuse_activation_hooks(report)
        sampler = CapturedSampler(model, num_steps=10)
        sampler(images, img_masks, tokens, masks, noise)

        def chunk():
            return static_sampling.sample_actions(model, images, img_masks, tokens, masks, noise, sampler.times,
                                                  sampler.ops, sampler._groups, sampler.prefix_sdpa)

        with sampler._kernel_choices():
            chunk()
            out[preset] = kernel_profile(chunk, top_n=400)
        print(preset, out[preset]["kernels"], out[preset]["kernel_time_ms"], round(time.time() - t0, 1), flush=True)
        with open(args.out, "w") as f:
            json.dump(out, f, indent=1)
        report.remove_hooks()
        del sampler


if __name__ == "__main__":
    main()
