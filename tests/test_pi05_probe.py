"""Fast-vs-eager probe: a cell on the captured sampler compares its first chunk with lerobot's eager
`sample_actions` before any episode, records the result in its header, and is refused when the
two differ beyond the bound (bit-equal on the CPU). Demo pi0.5: real lerobot 0.6.1 classes at
reduced width, random weights, float32, CPU."""

import re

import pytest
import torch
from test_runner_sampler import STUDY

from vlaquantbench.cells import cell_config
from vlaquantbench.errors import UserError
from vlaquantbench.models.adapter import PROBE_BOUNDS, AdapterConfig, make_adapter
from vlaquantbench.models.pi05.adapter import Pi05Adapter
from vlaquantbench.quant import QuantConfig, quantize_
from vlaquantbench.runner.cell import CellRun

CAPTURED = {**STUDY, "runner": {**STUDY["runner"], "sampler": "captured"}}


@pytest.fixture
def one_thread():
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


def test_a_captured_cell_records_a_bit_equal_probe_and_counts_only_episodes(tmp_path, one_thread):
    run = CellRun(cell_config("libero/libero_spatial/pi05/rtn-W4A4-e2e", CAPTURED), tmp_path,
                  progress=False)
    run.prepare()
    probe = run.header["inference"]["fast_path_probe"]
    assert probe == {"path": "captured", "device": "cpu", "max_abs_diff": 0.0, "rel_l2": 0.0,
                     "bound": {"max_abs_diff": 0.0}, "passed": True}
    # The probe's chunk ran every quantizer, but it is no evidence for the episodes: counts restart.
    assert set(run.report.hook_calls().values()) == {0}
    assert not any(tmp_path.iterdir())


_PREPARE = Pi05Adapter.prepare_inference


def _stale_groups(self, report):
    """A real fault of the fast path: weights changed after its linear groups copied them (the
    sampler's documented `reset()` not called), so it computes with the old q/k/v."""
    record = _PREPARE(self, report)
    self._captured._model_groups()
    with torch.no_grad():
        for layer in self.model.paligemma_with_expert.gemma_expert.model.layers:
            layer.self_attn.q_proj.weight.zero_()
    return record


def test_a_probe_beyond_its_bound_refuses_the_cell_before_any_episode(tmp_path, one_thread, monkeypatch):
    monkeypatch.setattr(Pi05Adapter, "prepare_inference", _stale_groups)
    run = CellRun(cell_config("libero/libero_spatial/pi05/rtn-W4A4-ah", CAPTURED), tmp_path, progress=False)
    with pytest.raises(UserError, match=r"fast path's first chunk differs from the eager policy's beyond its bound") as err:
        run.prepare()
    assert "'passed': False" in str(err.value) and "sampler: eager" in str(err.value)
    # Even on CUDA's bound this fault is caught: it is off by far more than bf16 rounding.
    assert float(re.search(r"'rel_l2': ([-+.e0-9]+)", str(err.value)).group(1)) > 2 * PROBE_BOUNDS["cuda"][1]
    assert not any(tmp_path.iterdir())


def test_eager_cells_have_no_probe():
    adapter = make_adapter(AdapterConfig(model="pi05", variant="demo", flow_steps=1, sampler="eager"))
    adapter.load()
    config = QuantConfig.from_preset("W4A4", scope="ah")
    quantize_(adapter.model, config, config.select(adapter.model, adapter.components))
    assert adapter.fast_path_probe() is None
