"""The capture-ready pi0.5 sampler returns lerobot's actions on the demo model (real lerobot 0.6.1
`PI05Pytorch` classes at reduced width, random weights, float32, CPU)."""

import pytest
import torch

from vlaquantbench.accel import CapturedSampler
from vlaquantbench.models import get_model_spec

# float32 end to end; the differences from lerobot are operation order only (SDPA / batched
# attention, AdaRMS modulations computed for all steps at once), so the chunks agree to rounding:
# measured relative L2 error 2e-7 (max abs 1.3e-6); the tolerance leaves 50x headroom.
REL_TOL = 1e-5


@pytest.fixture(scope="module")
def demo_model():
    return get_model_spec("pi05").build(variant="demo", device="cpu", seed=0)


def _inputs(batch: int, seed: int):
    g = torch.Generator().manual_seed(seed)
    images = [torch.rand(batch, 3, 224, 224, generator=g) * 2 - 1 for _ in range(3)]
    img_masks = [torch.ones(batch, dtype=torch.bool), torch.ones(batch, dtype=torch.bool), torch.zeros(batch, dtype=torch.bool)]
    tokens = torch.randint(0, 257152, (batch, 200), generator=g)
    masks = torch.ones(batch, 200, dtype=torch.bool)
    masks[0, 37:] = False  # a right-padded prompt, as the tokenizer produces
    noise = torch.randn(batch, 50, 32, generator=g)
    return images, img_masks, tokens, masks, noise


def _rel(a, b):
    return ((a - b).norm() / b.norm()).item()


def test_static_sampler_matches_lerobot_sample_actions(demo_model):
    images, img_masks, tokens, masks, noise = _inputs(batch=2, seed=1)
    expected = demo_model.sample_actions(images, img_masks, tokens, masks, noise=noise.clone(), num_steps=3)
    sampler = CapturedSampler(demo_model, num_steps=3)
    assert not sampler.use_graphs  # CPU: the static code runs eagerly
    actual = sampler(images, img_masks, tokens, masks, noise)
    assert actual.shape == expected.shape == (2, 50, 32)
    assert torch.isfinite(actual).all()
    assert _rel(actual, expected) < REL_TOL


def test_static_sampler_depends_on_the_observation(demo_model):
    """Guards against a sampler that ignores its inputs (e.g. a stale KV cache)."""
    images, img_masks, tokens, masks, noise = _inputs(batch=1, seed=2)
    sampler = CapturedSampler(demo_model, num_steps=2)
    base = sampler(images, img_masks, tokens, masks, noise)
    other_image = [images[0].flip(-1), images[1], images[2]]
    assert _rel(sampler(other_image, img_masks, tokens, masks, noise), base) > 1e-3
    assert _rel(sampler(images, img_masks, tokens.roll(1, dims=1), masks, noise), base) > 1e-3
