"""One action chunk of a demo pi0.5 or pi0 policy (lerobot's `sample_actions`) on seeded random inputs:
one camera, 16 prompt tokens, 2 flow steps, so the tests that need real layer inputs stay quick."""

import torch


def pi_chunk(model_name: str, model, seed: int, steps: int = 2) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    images, masks = [torch.rand(1, 3, 224, 224, generator=g) * 2 - 1], [torch.ones(1, dtype=torch.bool)]
    tokens = torch.randint(0, 257152, (1, 16), generator=g)
    args = [images, masks, tokens, torch.ones(1, 16, dtype=torch.bool)]
    if model_name == "pi0":  # pi0 takes the robot state as its own input (pi0.5 puts it in the prompt)
        args.append(torch.zeros(1, 32))
    return model.sample_actions(*args, noise=torch.randn(1, 50, 32, generator=g), num_steps=steps)
