"""Component scopes and named subsets on the four real architectures, built on the meta device:
the paper's `tab:vla_params` counts, every subset's count, the authors' recorded quant_report of
every reference cell, and the `vqb scopes` command's output and errors."""

import functools
import json

import pytest

from vlaquantbench.cells import quantized_counts
from vlaquantbench.cli import main as vqb
from vlaquantbench.errors import UserError
from vlaquantbench.models import get_model_spec
from vlaquantbench.quant import get_subset, select_layers, subsets_for
from paths import RECORDS

LIBERO_RECORDS = RECORDS / "libero"

# paper tab:vla_params: layers / parameters in millions (to 0.1M)
PAPER = {
    "pi05": {"ve": (162, 411.1), "mp": (1, 2.4), "llm": (126, 1981.8), "ah": (167, 430.0)},
    "pi0": {"ve": (162, 411.1), "mp": (1, 2.4), "llm": (126, 1981.8), "ah": (131, 314.7)},
    "openvla_oft": {"ve": (209, 728.3), "mp": (5, 88.2), "llm": (224, 6476.0), "ah": (4, 151.0)},
    "xvla": {"ve": (96, 335.0), "llm": (72, 151.0), "ah": (98, 304.1)},
}


@functools.cache
def meta_model(name):
    return get_model_spec(name).build("full", device="meta")


def counts(model, scope="e2e", only=None, exclude=None):
    return select_layers(meta_model(model), get_model_spec(model).components, scope, only, exclude).counts()


@pytest.mark.parametrize("model", sorted(PAPER))
def test_component_counts_match_the_paper(model):
    got = {c: (v["layers"], round(v["params"] / 1e6, 1)) for c, v in counts(model).items()}
    assert got == PAPER[model]


def test_xvla_has_no_mp_scope_and_oft_fc2_size():
    with pytest.raises(UserError, match="scope 'mp' selects no linear layer"):
        counts("xvla", "mp")
    assert counts("openvla_oft", "ah", only=["*.fc2"]) == {"ah": {"layers": 1, "params": 28672}}
    parts = {p: counts("xvla", "ah", only=[f"*.{p}"])["ah"]["params"] for p in ("qkv", "proj", "fc1", "fc2")}
    assert {p: round(v / 1e6, 1) for p, v in parts.items()} == {"qkv": 75.5, "proj": 25.2, "fc1": 100.7, "fc2": 100.7}


def test_vocab_heads_embeddings_and_norm_weights_are_never_selected():
    for model in PAPER:
        names = [n for group in select_layers(meta_model(model), get_model_spec(model).components, "e2e").layers.values()
                 for n in group]
        assert not [n for n in names if "lm_head" in n or "embed" in n]
    modules = dict(meta_model("xvla").named_modules())
    assert type(modules["transformer.action_decoder"]).__name__ == "DomainAwareLinear"  # embedding-based: excluded


ALL_SUBSETS = [(m, s) for m in PAPER for s in subsets_for(m)]


@pytest.mark.parametrize("model, name", ALL_SUBSETS, ids=[f"{m}-{s}" for m, s in ALL_SUBSETS])
def test_every_named_subset_gives_its_paper_count(model, name):
    subset = get_subset(model, name)
    got = counts(model, subset.scope, subset.only, subset.exclude)
    assert sum(c["layers"] for c in got.values()) == subset.layers
    if subset.params is not None:
        assert sum(c["params"] for c in got.values()) == subset.params


def test_issue_subsets_are_all_defined():
    required = {
        "pi05": ["onlyself_attn", "onlyadarms", "attn_adarms", "only_gate", "only_up", "only_down", "onlymlp",
                 "mlp_plus_adarms", "down_attn", "down_attn_adarms", "noadarms", "only_action_out",
                 "no_action_out", "s126_gateup", "s126_others"],
        "openvla_oft": ["only_fc1", "only_blocks", "only_fc2", "fc1_fc2", "no_ah_fc2"],
        "xvla": ["only_qkv", "only_proj", "only_fc1", "only_fc2", "onlymlp", "only_attn"],
    }
    for model, names in required.items():
        assert set(names) <= set(subsets_for(model)), model


def reference_cells():
    for path in sorted(LIBERO_RECORDS.glob("*/*/*.jsonl")):
        header = json.loads(path.open().readline())
        if header["preset"] != "BASELINE":
            yield pytest.param(path, header, id=f"{path.parent.parent.name}/{path.parent.name}/{path.stem}")


@pytest.mark.skipif(not LIBERO_RECORDS.is_dir(), reason="reference records not beside the checkout")
@pytest.mark.parametrize("path, header", list(reference_cells()) if LIBERO_RECORDS.is_dir() else [])
def test_authors_recorded_counts_are_reproduced(path, header):
    """Each reference cell's quant_report (layers and parameters per component) from its name: on the built
    architecture, and in total on the committed layer index, as the tables count cells known only from a summary."""
    model, scope = header["model"], header["scope"]
    parts = path.stem.split("-")
    subset = get_subset(model, parts[3]) if len(parts) > 3 else None
    got = counts(model, scope, subset and subset.only, subset and subset.exclude)
    recorded = {c: {"layers": v["layers"], "params": v["params"]}
                for c, v in header["quant_report"].items() if c != "act_calib"}
    assert got == recorded
    ref = "/".join(path.relative_to(RECORDS).with_suffix("").parts)
    assert quantized_counts(ref) == {key: sum(v[key] for v in recorded.values()) for key in ("layers", "params")}


def run_cli(capsys, *argv):
    code = vqb(["scopes", *argv])
    out = capsys.readouterr()
    return code, out.out, out.err


def test_cli_json_for_pi05(capsys):
    code, out, _ = run_cli(capsys, "pi05", "--json")
    data = json.loads(out)
    assert code == 0 and data["model"] == "pi05"
    assert {c: (v["layers"], round(v["params"] / 1e6, 1)) for c, v in data["components"].items()} == PAPER["pi05"]
    assert len(data["layers"]) == 456 and "action_out_proj" in data["layers"]
    assert "paligemma_with_expert.gemma_expert.model.layers.0.self_attn.q_proj" in data["layers"]


def test_cli_subset_and_component(capsys):
    code, out, _ = run_cli(capsys, "pi05", "--subset", "onlyadarms", "--json")
    data = json.loads(out)
    assert code == 0 and data["components"]["ah"]["layers"] == 36 and data["subset"]["matches"]
    code, out, _ = run_cli(capsys, "openvla_oft", "--component", "ah", "--only", "*mlp_resnet_blocks*", "--json")
    assert code == 0 and json.loads(out)["components"] == {"ah": {"layers": 2, "params": 33554432}}


@pytest.mark.parametrize("argv, message", [
    (["pi05", "--component", "ah", "--only", "*self_attn*", "*no_such_layer*"], "'*no_such_layer*'"),
    (["pi0", "--exclude", "*layernorm.dense"], "'*layernorm.dense'"),  # pi0 has no adaRMS
    (["pi05", "--subset", "no_such_subset"], "unknown subset 'no_such_subset'"),
    (["gpt2"], "unknown model 'gpt2'"),
    (["pi05", "--subset", "onlymlp", "--only", "*x*"], "--subset already defines"),
])
def test_cli_errors_name_the_problem(capsys, argv, message):
    code, _, err = run_cli(capsys, *argv)
    assert code != 0 and message in err


def test_oft_vision_forward_leaves_exactly_the_attention_pool_unfired():
    """The paper observes 204 of OFT's 209 VE layers: the policy reads SigLIP's patch features and
    never runs its attention-pooling head. A meta-device forward shows the same 5 unfired hooks."""
    import torch

    from vlaquantbench.quant import QuantConfig, quantize_

    model = meta_model("openvla_oft")
    config = QuantConfig.from_preset("W4A8", scope="ve")
    report = quantize_(model, config, config.select(model, get_model_spec("openvla_oft").components))
    try:
        pixels = torch.empty(1, 3, 224, 224, device="meta")
        assert model.vision_backbone(pixels, pixels).shape == (1, 256, 2176)
        assert report.unfired() == [f"vision_backbone.fused_featurizer.attn_pool.{n}"
                                    for n in ("q", "kv", "proj", "mlp.fc1", "mlp.fc2")]
        assert report.to_header()["hooks"]["fired"] == 204
    finally:
        report.remove_hooks()


@pytest.mark.parametrize("model", sorted(PAPER))
def test_committed_layer_index_is_the_real_architecture(model):
    """The workflow checks subset patterns against `models/<model>/linears.json` without torch, and the tables
    count #L and Params of summary-only cells on it; it must be what the real builders give (regenerate with
    `vqb scopes --write-index`): every layer's weight parameters on the full architecture, the same names
    for every variant."""
    from vlaquantbench.models.layer_index import linear_names, linear_params
    from vlaquantbench.quant.scope import eligible_linears

    spec = get_model_spec(model)
    built = eligible_linears(meta_model(model), spec.components)
    assert {c: {n: layer.weight.numel() for n, layer in g.items()} for c, g in built.items()} == linear_params(model)
    index = linear_names(model)
    for variant in set(spec.builders) - {"full"}:
        built = eligible_linears(spec.build(variant, device="meta"), spec.components)
        assert {c: list(g) for c, g in built.items()} == index, variant
