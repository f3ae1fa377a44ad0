"""Rollout calibration on real LIBERO episodes feeds a calibrated cell, with provenance in its header."""

import pytest
from demo_study import demo_study
import torch

from vlaquantbench.cells import calibration_config, cell_config
from vlaquantbench.quant.calibration import load_stats
from vlaquantbench.records import read_cell
from vlaquantbench.runner.calibration import calibrate
from vlaquantbench.runner.cell import run_cell

pytestmark = pytest.mark.slow

STUDY = demo_study(calibration={"episodes": 1, "first_init_state": 20})


def test_calibration_statistics_drive_a_calibrated_cell(tmp_path):
    cfg = cell_config("libero/libero_spatial/pi05/calib_ah-W4A4-ah-onlyself_attn", STUDY)
    calib = calibration_config(cfg)
    assert calib["calibration"]["init_states"] == [20] and calib["calibration"]["components"] == ["ah"]
    stats_path = calibrate(calib, tmp_path / "stats.pt", num_envs=1)
    stats = load_stats(stats_path)
    assert len(stats.layers) == 167  # every AH linear ran during the unquantized episode
    assert stats.keyed_fields["init_states"] == [20] and stats.keyed_fields["tasks"] == 1
    q_proj = stats.layers["paligemma_with_expert.gemma_expert.model.layers.0.self_attn.q_proj"]
    assert q_proj.calls == 2 * 1 and torch.all(q_proj.quantile <= q_proj.absmax)  # 1 chunk x 2 flow steps
    assert q_proj.hessian is None and q_proj.samples is None  # collected only for methods that declare them

    cell = read_cell(run_cell(cfg, tmp_path / "cell", calibration_stats=stats_path, num_envs=1, progress=False))
    report = cell.header["quant_report"]
    assert report["ah"]["layers"] == 72 and report["ah"]["calibrated_layers"] == 72
    assert report["act_calib"]["cache"] == f"{stats.key}.pt" and report["act_calib"]["alpha"] == 0.5
    assert cell.header["calibration"] == cfg["calibration"]
    assert cell.header["hooks"] == {"selected": 72, "fired": 72, "unfired": []}


def test_gptq_cell_takes_hessians_from_the_rollout_calibration(tmp_path):
    cfg = cell_config("libero/libero_spatial/pi05/gptq-W4A8-ah-onlyself_attn", STUDY)
    stats_path = calibrate(calibration_config(cfg), tmp_path / "stats.pt", num_envs=1)
    stats = load_stats(stats_path)
    assert stats.keyed_fields["hessian"] is True and stats.keyed_fields["sample_rows"] == 128
    q_proj = stats.layers["paligemma_with_expert.gemma_expert.model.layers.0.self_attn.q_proj"]
    # One short episode: 100 rows, all kept in the sample (stride 1), so X^T X is the sample's
    assert q_proj.rows == q_proj.samples.shape[0] == 100 and q_proj.sample_stride == 1
    x = q_proj.samples.double()
    assert torch.allclose(q_proj.hessian.double(), x.t() @ x, rtol=1e-5, atol=1e-4 * (x.t() @ x).abs().max().item())

    cell = read_cell(run_cell(cfg, tmp_path / "cell", calibration_stats=stats_path, num_envs=1, progress=False))
    report = cell.header["quant_report"]
    assert cell.header["quant_format"].startswith("GPTQ weights 4-bit asymmetric")
    assert report["gptq"]["error_vs_rtn_max"] <= 1.0 and report["ah"]["calibrated_layers"] == 72
    assert 0 < report["ah"]["mean_rel_mse"] < 1
    assert cell.header["hooks"] == {"selected": 72, "fired": 72, "unfired": []}


def test_step_static_cell_takes_per_step_scales_from_the_rollout_calibration(tmp_path):
    cfg = cell_config("libero/libero_spatial/pi05/step_static-W4A8-ah-onlyself_attn", STUDY)
    stats_path = calibrate(calibration_config(cfg), tmp_path / "stats.pt", num_envs=1)
    stats = load_stats(stats_path)
    assert stats.keyed_fields["step_scales"] is True and "hessian" not in stats.keyed_fields
    q_proj = stats.layers["paligemma_with_expert.gemma_expert.model.layers.0.self_attn.q_proj"]
    flow_steps = cfg["runner"]["flow_steps"]
    assert q_proj.calls == flow_steps and q_proj.step_absmax.shape == (flow_steps,)  # 1 chunk x 2 flow steps
    assert q_proj.step_absmax.max() == q_proj.absmax.max() and q_proj.step_absmax.min() < q_proj.step_absmax.max()

    cell = read_cell(run_cell(cfg, tmp_path / "cell", calibration_stats=stats_path, num_envs=1, progress=False))
    assert cell.header["quant_format"].startswith("RTN weights 4-bit asymmetric, group 128; activations 8-bit symmetric, "
                                                  "static per-tensor scales per flow step")
    assert cell.header["quant_report"]["step_static"] == {"per_step_layers": 72, "per_layer_layers": 0,
                                                          "flow_steps": flow_steps}
    assert cell.header["inference"]["sampler"] == "eager"
    assert cell.header["hooks"] == {"selected": 72, "fired": 72, "unfired": []}
