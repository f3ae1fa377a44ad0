"""The Hadamard transform (vlaquantbench.quant.transforms.Hadamard) on the demo pi0.5, pi0, X-VLA and
OpenVLA-OFT (real lerobot / timm / transformers architectures, random weights, float32): function
preserving without quantization, on the declared grids with every hook fired when composed with RTN,
and composed with GPTQ through rotated Hessians."""

import copy
import fnmatch

import pytest
import scipy.linalg
import torch
from pi_chunks import pi_chunk
from test_pi05_fast import _inputs, run_per_module

from vlaquantbench.errors import UserError
from vlaquantbench.models import get_model_spec
from vlaquantbench.models.registry import adapter_class
from vlaquantbench.quant import QuantConfig, quantize_, select_layers
from vlaquantbench.quant import calibration as calib
from vlaquantbench.quant.hadamard import BlockHadamard
from vlaquantbench.quant.input_transform import InputTransform
from vlaquantbench.quant.rotation import FoldedInput
from vlaquantbench.quant.transforms import Hadamard

MODELS = ("pi05", "pi0")


@pytest.fixture(scope="module")
def demos():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield {name: (get_model_spec(name), get_model_spec(name).build("demo", device="cpu", seed=0)) for name in MODELS}
    torch.set_num_threads(threads)


def test_block_hadamard_is_orthonormal_for_any_width():
    for width, block in ((256, 256), (96, 32), (1152, 128), (4304, 16), (1536, 512)):
        rotation = BlockHadamard(width)
        assert rotation.block == block
        # blocks past 128 channels are Kronecker products of small factors, equal to the dense matrix
        dense = torch.block_diag(*[torch.tensor(scipy.linalg.hadamard(block), dtype=torch.float64)] * (width // block))
        eye = torch.eye(width, dtype=torch.float64)
        assert torch.allclose(rotation.rotate(eye, torch.float64), dense / block ** 0.5, atol=1e-12)
        x = torch.randn(3, width, dtype=torch.float64)
        rotated = rotation.rotate(x, torch.float64)
        assert torch.allclose(rotated.norm(dim=1), x.norm(dim=1)) and not torch.allclose(rotated, x)
        assert torch.allclose(rotation.rotate(rotated, torch.float64), x)  # Sylvester H_b is symmetric: R R = I


def with_norm_gains(model, seed: int = 0):
    """A copy of `model` whose RMSNorm weights are seeded random values: a demo's are lerobot's
    zero initialisation (gain 1 + 0), which folding a gain into the next layers would not exercise."""
    model = copy.deepcopy(model)
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for module in model.modules():
            if "RMSNorm" in type(module).__name__ and isinstance(getattr(module, "weight", None), torch.Tensor):
                module.weight.copy_(torch.randn(module.weight.shape, generator=g) * 0.3)
    return model


@pytest.mark.parametrize("model_name", MODELS)
def test_rotated_unquantized_model_produces_the_same_actions(demos, model_name):
    spec, demo = demos[model_name]
    demo = with_norm_gains(demo)
    rotated = copy.deepcopy(demo)
    with torch.no_grad():
        reference = pi_chunk(model_name, demo, 3)
        config = QuantConfig.from_preset("BASELINE", scope="e2e", method="hadamard")
        report = quantize_(rotated, config, config.select(rotated, spec.components))
        actions = pi_chunk(model_name, rotated, 3)
    rel_l2 = ((actions - reference).norm() / reference.norm()).item()
    changed = sum(not torch.equal(layer.weight, demo.get_submodule(name).weight)
                  for name, layer in report.selection.flat().items())
    print(f"{model_name}: {changed} of {len(report.selection.flat())} e2e weights rotated, action rel L2 {rel_l2:.2e}")
    assert changed == len(report.selection.flat()) and report.unfired() == []
    assert rel_l2 <= 1e-4


def test_hadamard_w4a4_keeps_weights_and_inputs_on_the_grid(demos):
    spec, demo = demos["pi05"]
    policy = copy.deepcopy(demo)
    config = QuantConfig.from_preset("W4A4", scope="e2e", method="hadamard")
    report = quantize_(policy, config, config.select(policy, spec.components))
    with torch.no_grad():
        pi_chunk("pi05", policy, 3)
    header = report.to_header()
    assert header["hooks"] == {"selected": 456, "fired": 456, "unfired": []}
    assert header["quant_format"].endswith(Hadamard.description)
    for name, layer in report.selection.flat().items():
        groups = layer.weight.reshape(layer.out_features, -1, min(128, layer.in_features))
        assert max(len(torch.unique(row)) for row in groups.reshape(-1, groups.shape[-1])) <= 16, name
    hook = report.result.hooks["action_out_proj"]
    x = torch.randn(5, policy.get_submodule("action_out_proj").in_features)
    quantized = hook.transform(x)
    assert all(len(torch.unique(row)) <= 16 for row in quantized)  # 4-bit per token, after the rotation
    rotation = hook.transform.rotation
    assert torch.equal(quantized, InputTransform(act_bits=4)(rotation(x)))  # rotated, then quantized
    assert not torch.allclose(quantized, InputTransform(act_bits=4)(x))


VLM = "paligemma_with_expert.paligemma.model.language_model"
EXPERT = "paligemma_with_expert.gemma_expert.model"


def stream_at(model, model_name: str, root: str) -> torch.Tensor:
    """The residual stream entering layer 3 of the Gemma decoder at `root` (its input_layernorm's
    input), on the first call of one chunk."""
    seen = []
    handle = model.get_submodule(f"{root}.layers.3.input_layernorm").register_forward_pre_hook(
        lambda module, args: seen.append(args[0].clone()))
    try:
        pi_chunk(model_name, model, 3)
    finally:
        handle.remove()
    return seen[0]


@pytest.mark.parametrize("model_name", MODELS)
def test_streams_whose_rmsnorms_fold_are_rotated_offline(demos, model_name):
    """The VLM's Gemma stream (both models) and pi0's expert stream carry R h: their RMSNorms at unit
    gain, q/k/v weights W diag(1 + w) R^T, q/k/v and gate/up inputs not rotated by any hook;
    pi0.5's adaptive-norm expert keeps its stream and rotates every input online, as down_proj
    does everywhere."""
    spec, demo = demos[model_name]
    demo = with_norm_gains(demo)
    rotated = copy.deepcopy(demo)
    with torch.no_grad():
        config = QuantConfig.from_preset("BASELINE", scope="e2e", method="hadamard")
        quantize_(rotated, config, config.select(rotated, spec.components))
        for root, folds in ((VLM, True), (EXPERT, model_name == "pi0")):
            stream, original = stream_at(rotated, model_name, root), stream_at(demo, model_name, root)
            rotation = BlockHadamard(original.shape[-1])
            expected = rotation(original) if folds else original
            assert torch.allclose(stream, expected, atol=1e-5 * original.abs().max().item()), root
            norm = f"{root}.layers.0.input_layernorm"
            q_proj = f"{root}.layers.0.self_attn.q_proj"
            if folds:
                gain = 1 + demo.get_submodule(norm).weight
                assert gain.std() > 0 and torch.equal(rotated.get_submodule(norm).weight, torch.zeros_like(gain))
                folded = rotation.rotate(demo.get_submodule(q_proj).weight * gain, torch.float32)
                assert torch.allclose(rotated.get_submodule(q_proj).weight, folded, atol=1e-6)
        w4a4 = copy.deepcopy(demo)
        config = QuantConfig.from_preset("W4A4", scope="e2e", method="hadamard")
        selection = config.select(w4a4, spec.components)
        (hadamard,) = config.transforms
        declared_online = set(hadamard.runtime_step_layers(selection, None))  # asked before anything changes
        report = quantize_(w4a4, config, selection)
        pi_chunk(model_name, w4a4, 3)
    assert report.unfired() == []
    rotated_online = {name for name, hook in report.result.hooks.items() if hook.transform.rotation is not None}
    assert declared_online == rotated_online and 0 < len(rotated_online) < len(report.result.hooks)
    for root, folds in ((VLM, True), (EXPERT, model_name == "pi0")):
        for reader in ("self_attn.q_proj", "self_attn.v_proj", "mlp.gate_proj", "mlp.up_proj"):
            transform = report.result.hooks[f"{root}.layers.5.{reader}"].transform
            assert (transform.rotation is None) == folds and transform.act_bits == 4, (root, reader)
        for online in ("self_attn.o_proj", "mlp.down_proj"):
            assert isinstance(report.result.hooks[f"{root}.layers.5.{online}"].transform.rotation, BlockHadamard)
    final_reader = report.result.hooks["action_out_proj"].transform.rotation  # pi0: reads the expert's final norm
    assert (final_reader is None) == (model_name == "pi0")


def test_a_stream_no_selected_layer_reads_is_left_as_it_is(demos):
    """Scope `ah` of pi0 selects no reader of the VLM's stream: its weights and norms stay the
    released ones; the expert's stream is rotated (its norms at unit gain), the actions unchanged."""
    spec, demo = demos["pi0"]
    demo = with_norm_gains(demo)
    rotated = copy.deepcopy(demo)
    with torch.no_grad():
        config = QuantConfig.from_preset("BASELINE", scope="ah", method="hadamard")
        quantize_(rotated, config, config.select(rotated, spec.components))
        rel_l2 = ((pi_chunk("pi0", rotated, 3) - pi_chunk("pi0", demo, 3)).norm() / pi_chunk("pi0", demo, 3).norm()).item()
    changed = {name for name, p in demo.named_parameters() if not torch.equal(p, rotated.get_parameter(name))}
    vlm = [name for name, _ in demo.named_parameters() if name.startswith(VLM)]
    expert_layers = [name for name, _ in demo.named_parameters() if name.startswith(f"{EXPERT}.layers.")]
    assert vlm and not changed & set(vlm) and set(expert_layers) <= changed
    assert not rotated.get_submodule(f"{EXPERT}.norm").weight.any()  # folded into action_out_proj
    assert rel_l2 <= 1e-4


def test_hadamard_gptq_rounds_in_the_rotated_space(demos):
    spec, demo = demos["pi0"]
    demo = with_norm_gains(demo)
    layers = select_layers(demo, spec.components, "ah").flat()
    with torch.no_grad(), calib.observe(layers, quantile=None, sample_rows=128, hessian=True) as observer:
        pi_chunk("pi0", demo, 0)
    stats = observer.stats("hadgptq", {})
    name = "paligemma_with_expert.gemma_expert.model.layers.0.mlp.down_proj"
    rotation = BlockHadamard(layers[name].in_features)
    observed = stats.layers[name]
    assert observed.sample_stride == 1 and observed.rows == observed.samples.shape[0]  # every row kept
    rows = rotation.rotate(observed.samples.double(), torch.float64)
    expected = rows.t() @ rows  # the second moment of the rotated inputs
    mapped = rotation.map_hessian(observed.hessian.double())
    assert torch.allclose(mapped, expected, rtol=1e-5, atol=1e-5 * expected.abs().max().item())
    policy = copy.deepcopy(demo)
    smoothed = copy.deepcopy(demo)  # a folded reader's input is computed by the model: nothing can divide it first
    config = QuantConfig.from_preset("W4A8", scope="ah", method="hadamard_gptq", stats=stats,
                                     calibration=calib.CalibrationSettings(alpha=0.5, quantile=None))
    with pytest.raises(UserError, match="residual stream 'expert' cannot follow rollout smoothing of its reader "
                                        "paligemma_with_expert.gemma_expert.model.layers.0.self_attn.q_proj: "
                                        "run the Hadamard rotation without it"):
        quantize_(smoothed, config, config.select(smoothed, spec.components))
    # refused before the smoothing divided anything: the model is as it was
    assert all(torch.equal(a, b) for a, b in zip(smoothed.state_dict().values(), demo.state_dict().values(), strict=True))
    # a reader of the folded expert stream: its inputs become R (x / (1 + w)), its Hessian R D^-1 H D^-1 R^T
    reader = "paligemma_with_expert.gemma_expert.model.layers.0.self_attn.k_proj"
    gain = 1 + demo.get_submodule("paligemma_with_expert.gemma_expert.model.layers.0.input_layernorm").weight.double()
    rotation = BlockHadamard(layers[reader].in_features)
    observed = stats.layers[reader]
    rows = rotation.rotate(observed.samples.double() / gain, torch.float64)
    expected = rows.t() @ rows
    norm = "paligemma_with_expert.gemma_expert.model.layers.0.input_layernorm"
    folded = FoldedInput(rotation, gain.float(), norm)
    assert torch.allclose(folded.map_hessian(observed.hessian.double()), expected, rtol=1e-5,
                          atol=1e-5 * expected.abs().max().item())
    assert torch.allclose(folded.map_rows(observed.samples), rows.float(), atol=1e-5 * rows.abs().max().item())
    with pytest.raises(UserError, match=f"norm {norm} has gain 0 at channel 3"):
        FoldedInput(rotation, gain.float().index_fill(0, torch.tensor([3]), 0.0), norm).map_hessian(observed.hessian)
    with torch.no_grad():
        config = QuantConfig.from_preset("W4A8", scope="ah", method="hadamard_gptq", stats=stats)
        report = quantize_(policy, config, config.select(policy, spec.components))
        pi_chunk("pi0", policy, 3)
    header = report.to_header()
    assert header["hooks"] == {"selected": 131, "fired": 131, "unfired": []}
    assert header["quant_report"]["gptq"]["error_vs_rtn_max"] <= 1.0  # against RTN of the rotated weights
    assert 0 < header["quant_report"]["ah"]["mean_rel_mse"] < 1


def xvla_chunk(model, seed: int, steps: int = 2) -> torch.Tensor:
    """One X-VLA action chunk (the adapter's `act`: the Florence encoder once, then `steps` flow steps
    of the soft-prompted head) on seeded random inputs: two 224 px views, 64 prompt tokens, LIBERO's domain."""
    from vlaquantbench.models.xvla.components import PROPRIO_DIM

    g = torch.Generator().manual_seed(seed)
    images = torch.randn(1, 2, 3, 224, 224, generator=g)
    enc = model.forward_vlm(torch.randint(0, 1000, (1, 64), generator=g), images, torch.ones(1, 2, dtype=torch.bool))
    proprio = torch.randn(1, PROPRIO_DIM, generator=g)
    action = noise = torch.randn(1, model.chunk_size, model.dim_action, generator=g)
    for i in range(steps, 0, -1):
        t = torch.full((1,), i / steps)
        x_t = noise * t + action * (1 - t)
        proprio_m, x_t_m = model.action_space.preprocess(proprio, x_t)
        action = model.transformer(domain_id=torch.full((1,), 3), action_with_noise=x_t_m, proprio=proprio_m, t=t, **enc)
    return action


def oft_chunk(model, seed: int) -> torch.Tensor:
    """One OpenVLA-OFT forward (parallel decoding of its 8 x 7 actions) on seeded random inputs."""
    g = torch.Generator().manual_seed(seed)
    views = torch.randn(2, 3, 224, 224, generator=g)
    ids = torch.randint(3, model.language_model.config.vocab_size, (1, 12), generator=g)
    embeds = model.language_model.get_input_embeddings()(ids)
    return model(views, views.flip(-1), torch.rand(1, 8, generator=g) * 2 - 1, embeds)


CHUNKS = {"xvla": xvla_chunk, "openvla_oft": oft_chunk}


@pytest.fixture(scope="module")
def vla_demos():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield {name: (get_model_spec(name), get_model_spec(name).build("demo", device="cpu", seed=0).eval())
           for name in CHUNKS}
    torch.set_num_threads(threads)


@pytest.mark.parametrize("model_name", sorted(CHUNKS))
def test_rotated_xvla_and_oft_produce_the_same_actions(vla_demos, model_name):
    """Every selected linear of X-VLA (DaViT, BART encoder, the soft-prompted head, fused qkv included)
    and OFT (DINOv2 + SigLIP, projector, LLaMA, proprio projector, action MLP) takes the rotation;
    their convolutions (patch embeddings, DaViT's depthwise position convolutions) are not linears,
    never selected, and stay as they are."""
    spec, demo = vla_demos[model_name]
    rotated = copy.deepcopy(demo)
    chunk = CHUNKS[model_name]
    with torch.no_grad():
        reference = chunk(demo, 3)
        config = QuantConfig.from_preset("BASELINE", scope="e2e", method="hadamard")
        report = quantize_(rotated, config, config.select(rotated, spec.components))
        actions = chunk(rotated, 3)
    rel_l2 = ((actions - reference).norm() / reference.norm()).item()
    layers = report.selection.flat()
    changed = {name for name, layer in layers.items() if not torch.equal(layer.weight, demo.get_submodule(name).weight)}
    # a width with no even factor has the order-1 block: R = I, a weight left exactly as it was
    unrotatable = {name for name, layer in layers.items() if layer.in_features % 2}
    print(f"{model_name}: {len(changed)} of {len(layers)} e2e weights rotated ({len(unrotatable)} odd-width inputs), "
          f"action rel L2 {rel_l2:.2e}")
    assert changed == set(layers) - unrotatable and len(changed) > 0.9 * len(layers)
    assert report.unfired() == idle_layers(model_name, layers)
    assert rel_l2 <= 1e-4


def idle_layers(model_name: str, layers) -> list[str]:
    """The selected layers the model never runs (OFT's SigLIP attention-pooling head: its adapter's
    `idle_layers`), in selection order."""
    idle = getattr(adapter_class(model_name), "idle_layers", ())
    return [name for name in layers if any(fnmatch.fnmatch(name, pattern) for pattern in idle)]


@pytest.mark.parametrize("model_name", sorted(CHUNKS))
def test_xvla_and_oft_hadamard_w4a4_on_the_grid(vla_demos, model_name):
    spec, demo = vla_demos[model_name]
    policy = copy.deepcopy(demo)
    config = QuantConfig.from_preset("W4A4", scope="e2e", method="hadamard")
    report = quantize_(policy, config, config.select(policy, spec.components))
    with torch.no_grad():
        CHUNKS[model_name](policy, 3)
    hooks = report.to_header()["hooks"]
    idle = idle_layers(model_name, report.selection.flat())
    print(model_name, hooks)
    assert hooks["fired"] == hooks["selected"] - len(idle) and hooks["unfired"] == idle
    for name, layer in report.selection.flat().items():
        for group in layer.weight.split(128, dim=1):  # groups of 128 input columns, a shorter last one
            assert max(len(torch.unique(row)) for row in group) <= 16, name
        hook = report.result.hooks[name]
        x = torch.randn(3, layer.in_features)
        assert all(len(torch.unique(row)) <= 16 for row in hook.transform(x)), name


def test_captured_sampler_fuses_the_rotation_and_matches_the_eager_cell(demos):
    """pi0.5's captured sampler (its static code, run eagerly on the CPU) under W4A4 + Hadamard:
    every SigLIP and Gemma linear group is fused, its input (rotated online, except where the VLM's
    offline-rotated stream is read) quantized inside the op that produces it, once per group (q/k/v, gate/up), bit-identical to every linear called as a module
    through its own hook, with the same hook counts, and close to lerobot's eager chunk."""
    from vlaquantbench.models.pi05.fast import CapturedSampler
    from vlaquantbench.quant.hooks import Rotated

    spec, demo = demos["pi05"]
    policy = copy.deepcopy(demo)
    config = QuantConfig.from_preset("W4A4", scope="e2e", method="hadamard")
    report = quantize_(policy, config, config.select(policy, spec.components))
    images, img_masks, tokens, masks, noise = _inputs(batch=2, seed=1)
    with torch.no_grad():
        eager = policy.sample_actions(images, img_masks, tokens, masks, noise=noise.clone(), num_steps=2)
        report.reset_hook_calls()
        sampler = CapturedSampler(policy, num_steps=2)
        captured = sampler(images, img_masks, tokens, masks, noise)
        groups = sampler._groups
        layer_groups = [g for layer in groups.vision + groups.prefix + groups.expert
                        for g in (layer.qkv, layer.out, layer.mlp_in, layer.mlp_out)]
        # the VLM's q/k/v and gate/up read its offline-rotated stream: plain 4-bit quantization there
        offline = {id(g) for layer in groups.prefix for g in (layer.qkv, layer.mlp_in)}
        assert all(g.fused for g in layer_groups) and len(offline) == 2 * len(groups.prefix) > 0
        assert all(g.input_quantization == 4 if id(g) in offline else isinstance(g.input_quantization, Rotated)
                   for g in layer_groups)
        assert {g.input_quantization.quantization for g in layer_groups if id(g) not in offline} == {4}
        fused_calls = report.hook_calls()
        assert report.unfired() == []

        per_module = run_per_module(sampler, report, (images, img_masks, tokens, masks, noise))
    assert torch.equal(captured, per_module) and report.hook_calls() == fused_calls
    rel_l2 = ((captured - eager).norm() / eager.norm()).item()
    print(f"captured vs eager W4A4 hadamard: rel L2 {rel_l2:.2e}")
    assert rel_l2 < 1e-3


def test_a_shared_input_is_rotated_once():
    """q/k/v-like members reading one input: one rotation product and one quantization for all three."""
    from torch import nn

    from vlaquantbench.models.pi05.fast.linear_groups import LinearGroup
    from vlaquantbench.quant.hooks import CountingHook

    torch.manual_seed(0)
    layers = [nn.Linear(64, 8, bias=False) for _ in range(3)]
    hooks = [CountingHook(layer, InputTransform(rotation=BlockHadamard(64), act_bits=4)) for layer in layers]
    group = LinearGroup(layers)
    assert group.fused and group.input_quantization.rotation == BlockHadamard(64)
    x = torch.randn(5, 64)
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as profile:
        got = group(group.input_from(torch.clone, (x,)))
    # one rotation and one product of the three members (through their hooks: three of each)
    assert [e.name for e in profile.events()].count("aten::matmul") == 2
    assert [h.calls for h in hooks] == [1, 1, 1]
    expected = [layer(x) for layer in layers]  # through the hooks: each rotates and quantizes
    assert all(torch.allclose(a, b, rtol=1e-6, atol=1e-6) for a, b in zip(got, expected))  # one product vs three
