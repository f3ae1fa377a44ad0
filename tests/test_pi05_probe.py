"""Fast-vs-eager probe: a cell on the captured sampler compares its first chunk with lerobot's eager
`sample_actions` before any episode, records the result in its header, and is refused when the
two differ beyond the bound (on the CPU: `CPU_PROBE_FACTOR` times the eager policy's own spread when
its inputs move by one ulp). Demo pi0.5: real lerobot 0.6.1 classes at reduced width, random weights,
float32, CPU."""

import re

import pytest
import torch
from test_runner_sampler import STUDY

from vlaquantbench.cells import cell_config
from vlaquantbench.errors import UserError
from vlaquantbench.models.adapter import CPU_PROBE_FACTOR, CUDA_PROBE_BOUND, AdapterConfig, make_adapter, ulp_moved
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


def test_a_captured_cell_records_its_probe_within_its_bound_and_counts_only_episodes(tmp_path, one_thread):
    run = CellRun(cell_config("libero/libero_spatial/pi05/rtn-W4A4-e2e", CAPTURED), tmp_path,
                  progress=False)
    run.prepare()
    probe = run.header["inference"]["fast_path_probe"]
    assert set(probe) == {"path", "device", "max_abs_diff", "rel_l2", "eager_ulp_spread", "bound", "passed"}
    assert probe["path"] == "captured" and probe["device"] == "cpu" and probe["passed"]
    assert probe["bound"] == {"rel_l2": f"{CPU_PROBE_FACTOR} x eager_ulp_spread"}
    # 4-bit rounding flips make W4A4 end to end move far under one-ulp moves of its inputs (0.15 here).
    assert probe["rel_l2"] <= CPU_PROBE_FACTOR * probe["eager_ulp_spread"] and probe["eager_ulp_spread"] > 1e-3
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
    # The fault is off by far more than the action head's one-ulp spread, and even than CUDA's bound.
    rel_l2 = float(re.search(r"'rel_l2': ([-+.e0-9]+)", str(err.value)).group(1))
    spread = float(re.search(r"'eager_ulp_spread': ([-+.e0-9]+)", str(err.value)).group(1))
    assert rel_l2 > 2 * CUDA_PROBE_BOUND["rel_l2"] and rel_l2 > 1e5 * CPU_PROBE_FACTOR * spread
    assert not any(tmp_path.iterdir())


def test_eager_cells_have_no_probe():
    adapter = make_adapter(AdapterConfig(model="pi05", variant="demo", flow_steps=1, sampler="eager"))
    adapter.load()
    config = QuantConfig.from_preset("W4A4", scope="ah")
    quantize_(adapter.model, config, config.select(adapter.model, adapter.components))
    assert adapter.fast_path_probe() is None


def test_ulp_moved_moves_every_element_by_exactly_one_unit_in_the_last_place():
    x = torch.tensor([1.0, -1.0, 3.0e-39, 0.0, 1.0e30] * 20)
    moved = ulp_moved(x, torch.Generator().manual_seed(0))
    up, down = torch.nextafter(x, torch.tensor(torch.inf)), torch.nextafter(x, torch.tensor(-torch.inf))
    assert bool(((moved == up) | (moved == down)).all()) and bool((moved != x).all())
    assert bool((moved == up).any()) and bool((moved == down).any())
