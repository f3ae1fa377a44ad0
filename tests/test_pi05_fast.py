"""The capture-ready pi0.5 sampler returns lerobot's actions on the demo model (real lerobot 0.6.1
`PI05Pytorch` classes at reduced width, random weights, float32, CPU)."""

import pytest
import torch

from vlaquantbench.models.pi05.fast import CapturedSampler
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


class _Wrapped:
    """A transform the linear groups cannot see into: its layers run as modules, hooks included."""

    def __init__(self, transform):
        self.transform = transform

    def __call__(self, x):
        return self.transform(x)


def run_per_module(sampler, report, inputs):
    """The sampler's chunk again with every hook wrapped (`_Wrapped`), so no group can fuse it: each
    layer runs its own hook, the reference the fused groups must equal."""
    for hook in report.result.hooks.values():
        hook.transform = _Wrapped(hook.transform)
    report.reset_hook_calls()
    sampler.reset()
    per_module = sampler(*inputs)
    assert not any(g.fused for layer in sampler._groups.expert for g in (layer.qkv, layer.mlp_in))
    return per_module


def test_grouped_linears_with_fused_quantization_equal_the_hooks_exactly():
    """q/k/v and gate/up as one product each, per-token W4A4 quantization done by the producing norm
    or GELU: bit-identical (float32, CPU) to every linear called as a module through its own hook,
    with the same hook call counts."""
    from vlaquantbench.quant import QuantConfig, quantize_

    spec = get_model_spec("pi05")
    model = spec.build(variant="demo", device="cpu", seed=0)
    config = QuantConfig.from_preset("W4A4", scope="e2e")
    report = quantize_(model, config, config.select(model, spec.components))
    images, img_masks, tokens, masks, noise = _inputs(batch=2, seed=1)
    sampler = CapturedSampler(model, num_steps=2)
    grouped = sampler(images, img_masks, tokens, masks, noise)
    groups = sampler._groups
    layer_groups = [g for layer in groups.prefix + groups.expert for g in (layer.qkv, layer.out, layer.mlp_in, layer.mlp_out)]
    layer_groups += [g for layer in groups.vision for g in (layer.qkv, layer.out, layer.mlp_in, layer.mlp_out)]
    assert len(layer_groups) == 4 * (27 + 18 + 18)
    assert all(g.fused and g.input_quantization == 4 for g in layer_groups)
    grouped_calls = report.hook_calls()

    per_module = run_per_module(sampler, report, (images, img_masks, tokens, masks, noise))
    assert torch.equal(grouped, per_module)
    assert report.hook_calls() == grouped_calls
    assert report.unfired() == []


def test_a_calibrated_transform_keeps_its_layers_apart():
    """Smoothing vectors are per layer: such layers are never merged into one product."""
    from torch import nn

    from vlaquantbench.models.pi05.fast.linear_groups import LinearGroup
    from vlaquantbench.quant.hooks import CountingHook
    from vlaquantbench.quant.input_transform import InputTransform

    torch.manual_seed(0)
    layers = [nn.Linear(16, 8, bias=False) for _ in range(3)]
    plain = [CountingHook(layer, InputTransform(act_bits=8)) for layer in layers]
    assert LinearGroup(layers).fused
    plain[1].remove()
    CountingHook(layers[1], InputTransform(smooth=torch.rand(16) + 0.5, act_bits=8))
    group = LinearGroup(layers)
    assert not group.fused and group.input_quantization is None
    x = torch.randn(4, 16)
    expected = [layer(x) for layer in layers]
    assert all(torch.equal(a, b) for a, b in zip(group(group.input_from(torch.clone, (x,))), expected))
    with pytest.raises(ValueError, match="must come from its input_from"):
        group(x)


def test_float_format_members_share_one_product_and_their_hooks_result():
    from torch import nn

    from vlaquantbench.models.pi05.fast.linear_groups import LinearGroup
    from vlaquantbench.quant.hooks import CountingHook
    from vlaquantbench.quant.input_transform import InputTransform
    from vlaquantbench.quant.presets import FORMATS

    torch.manual_seed(0)
    layers = [nn.Linear(64, 8) for _ in range(3)]
    hooks = [CountingHook(layer, InputTransform(act_format=FORMATS["MXFP4"])) for layer in layers]
    group = LinearGroup(layers)
    assert group.fused and group.input_quantization is FORMATS["MXFP4"]
    x = torch.randn(2, 5, 64)
    expected = [layer(x) for layer in layers]  # through the hooks
    got = group(group.input_from(torch.clone, (x,)))
    assert all(torch.allclose(a, b, rtol=1e-6, atol=1e-6) for a, b in zip(got, expected))
    assert [h.calls for h in hooks] == [2, 2, 2]


def test_quantizing_ops_run_their_hand_written_kernels_only_where_they_apply():
    """The GELU ops name a hand-written GELU + per-token quantization kernel (`gelu_quant`, CUDA;
    checked bit for bit against the hooks on the GPU by benchmarks/gpu_policy_inference.py). Where it
    does not apply -- a CPU tensor here -- the compiled composition runs, so the result is the
    composition's: the op, then `quant.grid`."""
    from vlaquantbench.models.pi05.fast import gelu_quant
    from vlaquantbench.models.pi05.fast import static_sampling as pi05_static
    from vlaquantbench.quant import fused_kernel
    from vlaquantbench.quant.grid import fake_quant_activation
    from vlaquantbench.quant.hooks import quantizing_op

    g = torch.Generator().manual_seed(5)
    gate_up = (torch.randn(3, 7, 2 * 96, generator=g) * 2).to(torch.bfloat16)
    gate, up = gate_up.split(96, dim=-1)
    assert not fused_kernel.supports(gate)
    compiled = []

    def compiler(fn):  # stands in for inductor on the CPU; records that the composition was compiled
        compiled.append(fn.__name__)
        return fn

    got = quantizing_op(pi05_static.gelu_tanh_mul, 4, compiler)(gate, up)
    assert compiled == ["gelu_tanh_mul_then_int4"]
    assert torch.equal(got, fake_quant_activation(pi05_static.gelu_tanh_mul(gate, up), 4))
    siglip = torch.randn(5, 4304, generator=g)
    assert torch.equal(quantizing_op(pi05_static.gelu_tanh, 8, compiler)(siglip),
                       fake_quant_activation(pi05_static.gelu_tanh(siglip), 8))
    # The kernel reads the gate and up halves of the grouped gate/up product in place: rows with a
    # stride, no copy (a copy of both halves per call cost the W4A4 chunk 8% at batch 32 on an H200).
    rows = gelu_quant._rows(gate)
    assert rows.shape == (21, 96) and rows.stride() == (192, 1) and rows.data_ptr() == gate.data_ptr()
    # The vision tower's LayerNorms name a kernel for their output's quantization alone: the op is
    # compiled twice, with its quantization (run here) and by itself (on CUDA, then the kernel).
    compiled.clear()
    hidden, update = (torch.randn(2, 5, 1152, generator=g) * 3 for _ in range(2))
    weight, bias = torch.randn(1152, generator=g), torch.randn(1152, generator=g)
    _, normed = quantizing_op(pi05_static.add_layer_norm, 4, compiler)(hidden, update, weight, bias, 1e-6)
    assert compiled == ["add_layer_norm_then_int4", "add_layer_norm"]
    _, reference = pi05_static.add_layer_norm(hidden, update, weight, bias, 1e-6)
    assert torch.equal(normed, fake_quant_activation(reference, 4))


@pytest.mark.parametrize("kernel", ["gelu_quant_rows", "gelu_quant_row_chunks", "fused_kernel"])
def test_quantizing_triton_kernels_compile_for_hopper_with_ieee_quotients(kernel):
    """No GPU here, but Triton's own compiler runs: each quantizing kernel compiles to PTX for an
    H100/H200 (sm_90) and keeps the hooks' rounding -- the IEEE quotient (a correctly rounded
    reciprocal `div.rn` per row and the fused multiply-adds `fma.rn` of its exact correction, see
    the next test) and round-half-even (`cvt.rni`), not the approximate `/`."""
    triton = pytest.importorskip("triton")
    from triton.backends.compiler import GPUTarget
    from triton.compiler import ASTSource

    from vlaquantbench.models.pi05.fast import gelu_quant
    from vlaquantbench.quant import fused_kernel

    warps = 32
    if kernel.startswith("gelu_quant"):
        scalars = ("n_cols:i32", "gate_row_stride:i64", "up_row_stride:i64", "q_max:fp32", "inv_q_max:fp32",
                   "scale_floor:fp32", "k_beta:fp32", "k_kappa:fp32")
        pointers = ("gate_ptr", "up_ptr", "out_ptr")
        if kernel == "gelu_quant_rows":
            fn, constexprs = gelu_quant._gelu_fake_quant_rows, {"HAS_UP": True, "BLOCK": 16384}
        else:
            fn, constexprs = gelu_quant._gelu_fake_quant_row_chunks, {"HAS_UP": True, "CHUNK": gelu_quant.CHUNK}
            warps = gelu_quant.CHUNK_WARPS
    else:
        scalars = ("n_cols:i32", "q_max:fp32", "inv_q_max:fp32", "scale_floor:fp32")
        fn, pointers = fused_kernel._per_token_fake_quant, ("x_ptr", "y_ptr")
        scalars += ("smooth_ptr:*fp32", "clip_ptr:*fp32")  # per-channel vectors, float32
        constexprs = {"HAS_SMOOTH": True, "HAS_CLIP": True, "BLOCK": 2048}
    signature = {name: "*bf16" for name in pointers} | dict(s.split(":") for s in scalars)
    signature |= {name: "constexpr" for name in constexprs}
    compiled = triton.compile(ASTSource(fn=fn, signature=signature, constexprs=constexprs),
                              target=GPUTarget("cuda", 90, 32), options={"num_warps": warps})
    ptx = compiled.asm["ptx"]
    assert ".target sm_90" in ptx and "div.rn.f32" in ptx and "fma.rn.f32" in ptx and "cvt.rni.f32.f32" in ptx


def test_graph_plan_is_the_cheapest_cover_of_a_batch_by_the_captured_sizes():
    """Against every multiset of graph sizes covering the batch: least cost (a graph costs its size
    plus a fixed replay cost), then fewest graphs; each captured size runs alone, and larger batches
    split instead of padding to a graph twice their size."""
    import itertools

    from vlaquantbench.models.pi05.fast.captured import GRAPH_SIZES, REPLAY_COST_ROWS, graph_plan

    def cost(plan):
        return sum(plan) + REPLAY_COST_ROWS * len(plan)

    for batch in range(1, 37):
        plan = graph_plan(batch)
        assert list(plan) == sorted(plan, reverse=True) and set(plan) <= set(GRAPH_SIZES)
        assert sum(plan) >= batch and sum(plan) - plan[-1] < batch  # only the last graph pads
        covers = [c for n in range(1, 5) for c in itertools.combinations_with_replacement(GRAPH_SIZES, n) if sum(c) >= batch]
        least = min(cost(c) for c in covers)
        assert cost(plan) == pytest.approx(least), (batch, plan)
        assert len(plan) == min(len(c) for c in covers if cost(c) == pytest.approx(least))
    assert all(graph_plan(size) == (size,) for size in GRAPH_SIZES)
    assert graph_plan(13) == (12, 1) and graph_plan(17) == (16, 1) and graph_plan(32) == (16, 16)
    assert graph_plan(2, sizes=(1, 4), replay_cost_rows=0.5) == (1, 1)  # 3 rows of cost, not 4.5
    assert graph_plan(3, sizes=(1, 4), replay_cost_rows=2) == (4,)
    with pytest.raises(ValueError, match="at least one row"):
        graph_plan(0)
