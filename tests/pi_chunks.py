"""One action chunk of a demo pi0.5 or pi0 policy (lerobot's `sample_actions`) on seeded random inputs:
one camera, 16 prompt tokens, 2 flow steps, so the tests that need real layer inputs stay quick; the
inputs of a captured pi0.5 chunk; a transform the captured sampler's linear groups cannot see into."""

import torch


def pi_chunk(model_name: str, model, seed: int, steps: int = 2) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    images, masks = [torch.rand(1, 3, 224, 224, generator=g) * 2 - 1], [torch.ones(1, dtype=torch.bool)]
    tokens = torch.randint(0, 257152, (1, 16), generator=g)
    args = [images, masks, tokens, torch.ones(1, 16, dtype=torch.bool)]
    if model_name == "pi0":  # pi0 takes the robot state as its own input (pi0.5 puts it in the prompt)
        args.append(torch.zeros(1, 32))
    return model.sample_actions(*args, noise=torch.randn(1, 50, 32, generator=g), num_steps=steps)


def captured_inputs(batch: int, seed: int):
    """A pi0.5 chunk's inputs at the released shapes: three cameras (the third masked), 200 prompt
    tokens (the first row right-padded), noise."""
    g = torch.Generator().manual_seed(seed)
    images = [torch.rand(batch, 3, 224, 224, generator=g) * 2 - 1 for _ in range(3)]
    img_masks = [torch.ones(batch, dtype=torch.bool), torch.ones(batch, dtype=torch.bool), torch.zeros(batch, dtype=torch.bool)]
    tokens = torch.randint(0, 257152, (batch, 200), generator=g)
    masks = torch.ones(batch, 200, dtype=torch.bool)
    masks[0, 37:] = False  # a right-padded prompt, as the tokenizer produces
    noise = torch.randn(batch, 50, 32, generator=g)
    return images, img_masks, tokens, masks, noise


class OpaqueTransform:
    """A transform the linear groups cannot see into: its layers run as modules, hooks included."""

    def __init__(self, transform):
        self.transform = transform

    def __call__(self, x):
        return self.transform(x)
