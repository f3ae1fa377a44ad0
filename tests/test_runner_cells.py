"""Cell names in the authors' grammar -> canonical cell configs and their hashes."""

import csv

import pytest

from vlaquantbench.cells import calibration_config, cell_config, config_hash, parse_cell_name
from vlaquantbench.errors import UserError
from paths import REFERENCE

STUDY = {
    "models": {
        "pi05": {
            "variant": "demo",
            "checkpoint": "lerobot/pi05_libero_finetuned_v044",
            "revision": "8e174154ef5f6c60a8da12ae99c303d8963138c1",
        }
    },
    "tasks": 2,
    "episodes_per_task": 2,
    "runner": {"max_steps": 30, "camera_size": 128},
    "execution": {"num_envs": 4},
}


def ref(cell: str) -> str:
    return f"libero/libero_spatial/pi05/{cell}"


def test_every_cell_name_of_the_authors_parses():
    with open(REFERENCE / "authors-summary.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == 417
    for row in rows:
        fields = parse_cell_name(row["cell"])
        assert fields["preset"] == row["preset"], row["cell"]
        assert fields["scope"] == row["scope"].replace("+", "_"), row["cell"]  # summary spells ve+mp+llm
        assert fields["seed_offset"] == int(row["seed"]), row["cell"]


def test_subset_patterns_come_from_scopes_yaml():
    cfg = cell_config(ref("ablate-W4A4-ah-onlyself_attn"), STUDY)
    assert (cfg["method"], cfg["preset"], cfg["scope"], cfg["subset"]) == ("ablate", "W4A4", "ah", "onlyself_attn")
    assert cfg["only"] == ["*self_attn*"] and cfg["exclude"] is None
    assert cfg["tasks"] == [0, 1] and cfg["episodes_per_task"] == 2
    assert cfg["runner"]["max_steps"] == 30 and cfg["runner"]["camera_size"] == 128
    assert cfg["revision"] == STUDY["models"]["pi05"]["revision"]


def test_seed_steps_and_calibration_fields():
    cfg = cell_config(ref("seed2-steps1-calib_set1_all_a75-W4A4-e2e"), STUDY)
    assert cfg["seed"] == 2
    assert cfg["runner"]["flow_steps"] == 1
    assert cfg["calibration"] == {
        "components": ["ve", "mp", "llm", "ah"],
        "alpha": 0.75,
        "quantile": 0.999,
        "tasks": [0],
        "init_states": [22, 23],
        "seed": 2,
    }
    plain = cell_config(ref("calib_ah-W4A4-ah"), STUDY)["calibration"]
    assert plain["components"] == ["ah"] and plain["alpha"] == 0.5 and plain["init_states"] == [20, 21]


def test_hash_is_stable_and_covers_what_changes_episodes():
    base = cell_config(ref("ablate-W4A4-ah-onlyself_attn"), STUDY)
    assert config_hash(base) == config_hash(cell_config(ref("ablate-W4A4-ah-onlyself_attn"), dict(STUDY)))
    assert len(config_hash(base)) == 12 and int(config_hash(base), 16) >= 0
    variants = [
        ref("ablate-W4A8-ah-onlyself_attn"),
        ref("ablate-W4A4-ah-onlyadarms"),
        ref("seed1-ablate-W4A4-ah-onlyself_attn"),
        "libero/libero_object/pi05/ablate-W4A4-ah-onlyself_attn",
    ]
    hashes = {config_hash(cell_config(r, STUDY)) for r in variants}
    assert len(hashes) == len(variants) and config_hash(base) not in hashes
    for change in ({"episodes_per_task": 3}, {"tasks": [0]}, {"runner": {"max_steps": 31}}, {"seed": 5}):
        assert config_hash(cell_config(ref("ablate-W4A4-ah-onlyself_attn"), {**STUDY, **change})) != config_hash(base)


def test_execution_options_do_not_change_the_hash():
    base = cell_config(ref("rtn-W4A4-ah"), STUDY)
    other = cell_config(ref("rtn-W4A4-ah"), {**STUDY, "execution": {"num_envs": 1, "torch_threads": 2}})
    assert config_hash(base) == config_hash(other)


def test_calibrated_cells_share_statistics_across_presets():
    a = calibration_config(cell_config(ref("calib_ah-W4A4-ah"), STUDY))
    b = calibration_config(cell_config(ref("calib_ah-W4A8-ah"), STUDY))
    assert a == b and config_hash(a) == config_hash(b)
    assert calibration_config(cell_config(ref("rtn-W4A4-ah"), STUDY)) is None
    assert config_hash(cell_config(ref("calib_ah-W4A4-ah"), STUDY)) != config_hash(cell_config(ref("calib_ah-W4A8-ah"), STUDY))


@pytest.mark.parametrize(
    "cell, message",
    [
        ("W4A4-ah", "does not follow"),
        ("rtn-W4A4-head", "does not follow"),
        ("quip-W4A4-ah", "unknown method 'quip'"),
        ("calib_mp-W4A4-ah", "calib[_set<k>]"),
        ("calib_llm-W4A4-ah", "outside scope 'ah'"),
        ("ablate-W4A4-ah-nosuchsubset", "unknown subset 'nosuchsubset'"),
        ("rtn-W9Z-ah", "unknown quantization preset 'W9Z'"),
        ("nf4-W8A8-ah", "method 'nf4' implements W4; preset 'W8A8' does not match"),
        ("fp8-W4A8-ah", "method 'fp8' implements W8A8; preset 'W4A8' does not match"),
        ("awq-W4A8-ah", r"method 'awq' is weight-only \(W<b>\[G<g>\]\); preset 'W4A8' does not match"),
    ],
)
def test_bad_cell_names_are_user_errors_naming_the_cell(cell, message):
    with pytest.raises(UserError, match=message) as err:
        cell_config(ref(cell), STUDY)
    assert cell in str(err.value)


def test_unknown_model_and_bad_reference():
    with pytest.raises(UserError, match="model 'pi0' is not in study.models"):
        cell_config("libero/libero_spatial/pi0/rtn-W4-e2e", STUDY)
    with pytest.raises(UserError, match="<benchmark>/<suite>/<model>/<cell>"):
        cell_config("libero_spatial/pi05/rtn-W4-e2e", STUDY)


def test_awq_cells_calibrate_every_scope_component_with_sampled_rows():
    cfg = cell_config(ref("awq-W4-llm"), STUDY)
    assert cfg["method"] == "awq" and cfg["preset"] == "W4" and cfg["scope"] == "llm"
    assert cfg["calibration"] == {
        "components": ["llm"],
        "alpha": None,
        "quantile": None,
        "sample_rows": 128,
        "tasks": [0],
        "init_states": [20, 21],
        "seed": 0,
    }
    calib = calibration_config(cfg)
    assert calib["calibration"] == cfg["calibration"] and calib["runner"]["sampler"] == "eager"
    assert calibration_config(cell_config(ref("awq-W3-llm"), STUDY)) == calib  # W3 and W4 share statistics
    e2e = cell_config(ref("awq-W4-e2e"), STUDY)["calibration"]
    assert e2e["components"] == ["ve", "mp", "llm", "ah"] and e2e["sample_rows"] == 128
    assert config_hash(cfg) != config_hash(cell_config(ref("rtn-W4-llm"), STUDY))


def test_smoothquant_cells_smooth_by_default_with_the_papers_alpha():
    cfg = cell_config(ref("smoothquant-W8A8-llm"), STUDY)
    assert cfg["calibration"] == {
        "components": ["llm"],
        "alpha": 0.85,
        "quantile": None,
        "tasks": [0],
        "init_states": [20, 21],
        "seed": 0,
    }
    assert calibration_config(cfg)["calibration"] == cfg["calibration"]


def test_float_format_presets_are_reachable_from_cell_names():
    cfg = cell_config(ref("rtn-MXFP4-ah"), STUDY)
    assert cfg["preset"] == "MXFP4" and cfg["calibration"] is None
    assert config_hash(cfg) != config_hash(cell_config(ref("rtn-NVFP4-ah"), STUDY))
    assert cell_config(ref("rtn-W4AMXFP4-e2e"), STUDY)["preset"] == "W4AMXFP4"
    with pytest.raises(UserError, match="MXFP8E4M3"):
        cell_config(ref("rtn-MXFP8-ah"), STUDY)


def test_every_registered_method_is_reachable_from_a_cell_name():
    from vlaquantbench.cells import quantizer_method
    from vlaquantbench.quant.methods import METHODS, registered_methods

    assert {"int4wo", "fp8", "fp8_tensor", "fp8_static"} <= set(registered_methods())
    presets = {"nf4": "W4", "int8": "W8", "int4wo": "W4", "awq": "W4"}  # the presets these implement
    for method in registered_methods():
        cfg = cell_config(ref(f"{method}-{presets.get(method, 'W8A8')}-ah"), STUDY)
        assert cfg["method"] == method and quantizer_method(method) == method
        assert callable(METHODS[method].resolve())  # the implementation the registry names exists
        recorded = METHODS[method].calibration_fields()
        if recorded is None:
            assert cfg["calibration"] is None
        else:  # calibration episodes of the scope collect what the method needs
            assert cfg["calibration"]["components"] == ["ah"] and cfg["calibration"]["quantile"] is None
            assert {k: cfg["calibration"].get(k) for k in recorded} == recorded
            assert cfg["calibration"]["alpha"] == recorded.get("alpha")
    assert quantizer_method("ablate") == quantizer_method("calib_ah") == "rtn"


def test_cell_configs_are_built_without_torch():
    """The workflow builds every cell's config while it parses; that must not import torch."""
    import subprocess
    import sys

    code = ("import sys; from vlaquantbench.cells import cell_config; "
            f"cell_config({ref('ablate-W4A4-ah-onlyself_attn')!r}, {STUDY!r}); "
            "assert 'torch' not in sys.modules, sorted(m for m in sys.modules if m.startswith('torch'))[:3]")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr


def test_typed_cell_round_trips_its_canonical_form():
    from vlaquantbench.cells import CellConfig

    for cell in ("ablate-W4A4-ah-onlyself_attn", "seed2-steps1-calib_set1_all_a75-W4A4-e2e", "awq-W4-llm"):
        cfg = cell_config(ref(cell), STUDY)
        typed = CellConfig.from_dict(cfg)
        assert typed.to_dict() == cfg and typed.config_hash == config_hash(cfg)


def test_gptq_cells_calibrate_hessians_and_rows_for_every_model_and_scope():
    from demo_study import CHECKPOINTS, demo_study

    study = demo_study(*CHECKPOINTS)
    built = 0
    for model in CHECKPOINTS:
        for scope in ("ve", "mp", "llm", "ah", "e2e", "ve_mp_llm"):
            try:
                cell_config(f"libero/libero_spatial/{model}/rtn-W4-{scope}", study)
            except UserError:  # a scope the model lacks (X-VLA has no MP)
                continue
            built += 1
            for cell in (f"gptq-W4-{scope}", f"gptq_act-W4A8-{scope}"):
                calibration = cell_config(f"libero/libero_spatial/{model}/{cell}", study)["calibration"]
                assert calibration["hessian"] is True and calibration["sample_rows"] == 128, (model, cell)
                assert calibration["alpha"] is None and calibration["quantile"] is None
    assert built >= 21
    cfg = cell_config(ref("gptq-W4A4-llm"), STUDY)
    # GPTQ's statistics are their own cache; RTN-smoothing and AWQ caches keep their keys and forms
    assert calibration_config(cfg) != calibration_config(cell_config(ref("awq-W4-llm"), STUDY))
    assert "hessian" not in cell_config(ref("awq-W4-llm"), STUDY)["calibration"]
    assert calibration_config(cfg) == calibration_config(cell_config(ref("gptq-W3G64-llm"), STUDY))
    with pytest.raises(UserError, match=r"cell 'libero/libero_spatial/pi05/gptq-MXFP4-ah': method 'gptq' implements"):
        cell_config(ref("gptq-MXFP4-ah"), STUDY)


def test_a_method_needing_statistics_no_calibration_collects_is_refused_naming_it():
    from vlaquantbench.quant.methods import METHODS, register_method

    # a plugin's own kind: nothing in the rollout calibration collects it
    register_method("fisherscaled", lambda model, selection, config: None, statistics=["fisher"])
    try:
        with pytest.raises(UserError, match=r"cell 'libero/libero_spatial/pi05/fisherscaled-W4A8-ah': method "
                                            r"'fisherscaled' needs calibration statistics fisher, which the rollout "
                                            r"calibration does not collect \(it collects absmax, rows, hessian, step_scales\)"):
            cell_config(ref("fisherscaled-W4A8-ah"), STUDY)
    finally:
        del METHODS["fisherscaled"]


def test_step_static_cells_calibrate_step_scales_and_quantize_activations():
    cfg = cell_config(ref("step_static-W4A4-ah"), STUDY)
    assert cfg["calibration"]["step_scales"] is True and cfg["calibration"]["components"] == ["ah"]
    assert cfg["calibration"]["alpha"] is None and cfg["calibration"]["quantile"] is None
    # its own cache: per-step scales are not in the GPTQ or RTN-smoothing statistics
    assert calibration_config(cfg) != calibration_config(cell_config(ref("gptq-W4A4-ah"), STUDY))
    assert "step_scales" not in cell_config(ref("gptq-W4A4-ah"), STUDY)["calibration"]
    assert calibration_config(cfg) == calibration_config(cell_config(ref("step_static-W8A8-ah"), STUDY))
    with pytest.raises(UserError, match=r"/step_static-W4-ah': method 'step_static' quantizes activations with "
                                        r"static scales: it implements W<b>\[G<g>\]A<a>; preset 'W4'"):
        cell_config(ref("step_static-W4-ah"), STUDY)
