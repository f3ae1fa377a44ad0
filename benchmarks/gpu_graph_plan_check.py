"""The captured sampler's graph plans (`captured.graph_plan`: a batch split over several graphs, the
last padded) against lerobot's eager `sample_actions`, row by row, on distinct observations.

    python benchmarks/gpu_graph_plan_check.py --out benchmarks/results/gpu_graph_plan_check.json
    .venv/bin/python benchmarks/gpu_graph_plan_check.py --device cpu --variant demo --dtype float32 --out /tmp/check.json

Per batch: its plan, the largest and median relative L2 of a row against the eager row, and row 0
against eager row 1 (what a row that landed in the wrong place would show), and the first call's
seconds (with the captures it needed). On the CPU the sampler
runs eagerly, without graphs.
"""

import argparse
import json
import time

import numpy as np
import torch

from vlaquantbench.models.adapter import AdapterConfig, episode_generator, make_adapter
from vlaquantbench.models.pi05.fast.captured import graph_plan
from vlaquantbench.models.pi_family_adapter import LIBERO_CAMERAS, STATE_DIM

INSTRUCTIONS = ("pick up the black bowl and place it on the plate", "open the drawer")


def relative(a: torch.Tensor, b: torch.Tensor) -> float:
    return ((a - b).float().norm() / b.float().norm()).item()


@torch.no_grad()
def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--variant", default="random", choices=["random", "demo"])
    parser.add_argument("--dtype", default="bfloat16")
    parser.add_argument("--batches", type=int, nargs="+", default=[13, 17, 5, 1])
    parser.add_argument("--out", default="benchmarks/results/gpu_graph_plan_check.json")
    args = parser.parse_args()
    adapter = make_adapter(AdapterConfig(model="pi05", variant=args.variant, device=args.device, dtype=args.dtype,
                                         sampler="captured"))
    adapter.load()
    adapter.prepare_inference(None)
    rng = np.random.default_rng(0)
    result = {}
    for batch_size in args.batches:
        observations = [{**{view: rng.integers(0, 256, (224, 224, 3), dtype=np.uint8) for view in LIBERO_CAMERAS},
                         "state": rng.uniform(-0.05, 0.05, STATE_DIM).astype(np.float32),
                         "instruction": INSTRUCTIONS[i % 2]} for i in range(batch_size)]
        batch = adapter.preprocessor(adapter._lerobot_batch(observations))
        images, masks = adapter._images(batch)
        shape = (batch_size, adapter.predicted_chunk, int(adapter.policy_config.max_action_dim))
        noise = torch.randn(shape, generator=episode_generator(batch_size)).to(adapter._device)
        began = time.perf_counter()
        fast = adapter._sample(batch, images, masks, noise.clone())  # captures the plan's new graph sizes
        first_call_s = time.perf_counter() - began
        eager = adapter.model.sample_actions(images, masks, batch["observation.language.tokens"],
                                             batch["observation.language.attention_mask"], noise=noise.clone(),
                                             num_steps=adapter.config.flow_steps)
        rows = [relative(fast[i], eager[i]) for i in range(batch_size)]
        result[batch_size] = {"plan": graph_plan(batch_size), "rel_l2_max": max(rows), "rel_l2_median": float(np.median(rows)),
                              "row0_vs_eager_row1": relative(fast[0], eager[1]) if batch_size > 1 else None,
                              "first_call_s": round(first_call_s, 2)}
        print(batch_size, result[batch_size], flush=True)
    with open(args.out, "w") as out:
        json.dump(result, out, indent=1)


if __name__ == "__main__":
    main()
