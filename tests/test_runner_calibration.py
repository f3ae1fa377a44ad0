"""Rollout calibration on real LIBERO episodes feeds a calibrated cell, with provenance in its header."""

import json
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
from demo_study import demo_study
import torch

from vlaquantbench.cells import calibration_config, cell_config
from vlaquantbench.quant.calibration import load_stats
from vlaquantbench.records import read_cell

pytestmark = pytest.mark.slow

STUDY = demo_study(calibration={"episodes": 1, "first_init_state": 20})
CALIBRATE_THEN_RUN = (
    "import json, sys; from pathlib import Path; from vlaquantbench.runner.calibration import calibrate; "
    "from vlaquantbench.runner.cell import run_cell; cfg, folder = json.loads(sys.argv[1]), Path(sys.argv[2]); "
    "stats = calibrate(json.loads(sys.argv[3]), folder / 'stats.pt', num_envs=1); "
    "run_cell(cfg, folder / 'cell', calibration_stats=stats, num_envs=1, progress=False); print(stats)")
CELLS = ["libero/libero_spatial/pi05/calib_ah-W4A4-ah-onlyself_attn",
         "libero/libero_spatial/pi05/gptq-W4A8-ah-onlyself_attn",
         "libero/libero_spatial/pi05/step_static-W4A8-ah-onlyself_attn"]


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    """Each test's rollout calibration (`calibrate`, one env) and then its calibrated cell (`run_cell` with those
    statistics), in an interpreter of its own, two such runs at a time (each keeps about one core busy), all started
    when the first test needs one: a function from a cell's reference to (its statistics file, its cell folder)."""
    root = tmp_path_factory.mktemp("calibrated")

    def calibrate_then_run(folder, cfg):
        folder.mkdir()
        done = subprocess.run([sys.executable, "-c", CALIBRATE_THEN_RUN, json.dumps(cfg), str(folder),
                               json.dumps(calibration_config(cfg))], capture_output=True, text=True, timeout=1500)
        assert done.returncode == 0, done.stderr[-3000:]
        return Path(done.stdout.strip().splitlines()[-1]), folder / "cell"

    # The configs built here, in this thread (the benchmark registry is read, hence filled, on first use).
    configs = {ref: cell_config(ref, STUDY) for ref in CELLS}
    with ThreadPoolExecutor(2) as pool:
        runs = {ref: pool.submit(calibrate_then_run, root / f"cell{n}", configs[ref]) for n, ref in enumerate(CELLS)}
        yield lambda ref: runs[ref].result()


def test_calibration_statistics_drive_a_calibrated_cell(calibrated):
    cfg = cell_config(CELLS[0], STUDY)
    calib = calibration_config(cfg)
    assert calib["calibration"]["init_states"] == [20] and calib["calibration"]["components"] == ["ah"]
    stats_path, cell_folder = calibrated(CELLS[0])
    stats = load_stats(stats_path)
    assert len(stats.layers) == 167  # every AH linear ran during the unquantized episode
    assert stats.keyed_fields["init_states"] == [20] and stats.keyed_fields["tasks"] == 1
    q_proj = stats.layers["paligemma_with_expert.gemma_expert.model.layers.0.self_attn.q_proj"]
    assert q_proj.calls == 2 * 1 and torch.all(q_proj.quantile <= q_proj.absmax)  # 1 chunk x 2 flow steps
    assert q_proj.hessian is None and q_proj.samples is None  # collected only for methods that declare them

    cell = read_cell(cell_folder)
    report = cell.header["quant_report"]
    assert report["ah"]["layers"] == 72 and report["ah"]["calibrated_layers"] == 72
    assert report["act_calib"]["cache"] == f"{stats.key}.pt" and report["act_calib"]["alpha"] == 0.5
    assert cell.header["calibration"] == cfg["calibration"]
    assert cell.header["hooks"] == {"selected": 72, "fired": 72, "unfired": []}


def test_gptq_cell_takes_hessians_from_the_rollout_calibration(calibrated):
    stats_path, cell_folder = calibrated(CELLS[1])
    stats = load_stats(stats_path)
    assert stats.keyed_fields["hessian"] is True and stats.keyed_fields["sample_rows"] == 128
    q_proj = stats.layers["paligemma_with_expert.gemma_expert.model.layers.0.self_attn.q_proj"]
    # One short episode: 100 rows, all kept in the sample (stride 1), so X^T X is the sample's
    assert q_proj.rows == q_proj.samples.shape[0] == 100 and q_proj.sample_stride == 1
    x = q_proj.samples.double()
    assert torch.allclose(q_proj.hessian.double(), x.t() @ x, rtol=1e-5, atol=1e-4 * (x.t() @ x).abs().max().item())

    cell = read_cell(cell_folder)
    report = cell.header["quant_report"]
    assert cell.header["quant_format"].startswith("GPTQ weights 4-bit asymmetric")
    assert report["gptq"]["error_vs_rtn_max"] <= 1.0 and report["ah"]["calibrated_layers"] == 72
    assert 0 < report["ah"]["mean_rel_mse"] < 1
    assert cell.header["hooks"] == {"selected": 72, "fired": 72, "unfired": []}


def test_step_static_cell_takes_per_step_scales_from_the_rollout_calibration(calibrated):
    cfg = cell_config(CELLS[2], STUDY)
    stats_path, cell_folder = calibrated(CELLS[2])
    stats = load_stats(stats_path)
    assert stats.keyed_fields["step_scales"] is True and "hessian" not in stats.keyed_fields
    q_proj = stats.layers["paligemma_with_expert.gemma_expert.model.layers.0.self_attn.q_proj"]
    flow_steps = cfg["runner"]["flow_steps"]
    assert q_proj.calls == flow_steps and q_proj.step_absmax.shape == (flow_steps,)  # 1 chunk x 2 flow steps
    assert q_proj.step_absmax.max() == q_proj.absmax.max() and q_proj.step_absmax.min() < q_proj.step_absmax.max()

    cell = read_cell(cell_folder)
    assert cell.header["quant_format"].startswith("RTN weights 4-bit asymmetric, group 128; activations 8-bit symmetric, "
                                                  "static per-tensor scales per flow step")
    assert cell.header["quant_report"]["step_static"] == {"per_step_layers": 72, "per_layer_layers": 0,
                                                          "flow_steps": flow_steps}
    assert cell.header["inference"]["sampler"] == "eager"
    assert cell.header["hooks"] == {"selected": 72, "fired": 72, "unfired": []}
