"""`study.runner.sampler`: the captured pi0.5 sampler in the runner, its resolution and its header record
(demo pi0.5: real lerobot 0.6.1 classes at reduced width, random weights, float32, CPU)."""

import numpy as np
import pytest
from demo_study import demo_study
import torch
from test_pi05_fast import REL_TOL
from test_runner_adapter import observations

from vlaquantbench.cells import CellConfig, cell_config, config_hash
from vlaquantbench.errors import UserError
from vlaquantbench.models.adapter import AdapterConfig, make_adapter, resolve_sampler
from vlaquantbench.models.registry import adapter_class
from vlaquantbench.quant import QuantConfig, quantize_
from vlaquantbench.runner.cell import CellRun

STUDY = demo_study("pi05", "pi0", flow_steps=1)


def _rel(a, b) -> float:
    """Relative L2 error, as `REL_TOL` (1e-5, float32 operation order only) is stated."""
    return float(np.linalg.norm(np.asarray(a) - np.asarray(b)) / np.linalg.norm(np.asarray(b)))


class _Recording:
    """Wraps a hook's transform: appends (layer, input, quantized output) of every call."""

    def __init__(self, transform, name, calls):
        self.transform, self.name, self.calls = transform, name, calls

    def __call__(self, x):
        y = self.transform(x)
        self.calls.append((self.name, x.detach().clone(), y.detach().clone()))
        return y


def _act_ah(sampler: str, obs, seeds, preset="W4A4"):
    adapter = make_adapter(AdapterConfig(model="pi05", variant="demo", flow_steps=1, sampler=sampler))
    adapter.load()
    config = QuantConfig.from_preset(preset, scope="ah")
    report = quantize_(adapter.model, config, config.select(adapter.model, adapter.components))
    inference = adapter.prepare_inference(report)
    calls = []
    for name, hook in report.result.hooks.items():
        hook.transform = _Recording(hook.transform, name, calls)
    chunks = adapter.act(obs, [adapter.reset(s) for s in seeds])
    return chunks, calls, report, inference


@pytest.fixture
def one_thread():
    """The runner's jobs compute with one torch thread (`CellRun(torch_threads=1)`); the thread count
    changes CPU GEMM blocking, hence the last bits, hence which rounding decisions flip."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


# NVFP4: a float format (its linear groups run member by member through the hooks) whose input scale
# is per sample, so the captured path must hand every layer the same sample-major input as eager.
@pytest.mark.parametrize("preset", ["W4A4", "NVFP4"])
def test_captured_sampler_returns_the_eager_actions_under_4_bit_ah(one_thread, preset):
    """Every episode's chunk equals the eager one to REL_TOL, unless a 4-bit rounding decision flipped
    on a last-bit difference: then the first quantized activation that differs (in the eager order of
    calls) was computed from inputs that agree to REL_TOL. Such a flip moves one value by a whole grid
    step, and the random-weight demo amplifies it to ~10% of the chunk (measured with one thread: 1 of
    16 episodes at one flow step, 5 of 16 at three), so a plain tolerance on actions cannot hold under
    W4A4. Measured here: episodes 1-3 agree to 2e-7; episode 0 flips in layer 4's o_proj (inputs
    agree to 1.3e-7, chunk off by 0.11)."""
    obs, seeds = observations(4, seed=0), [0, 1, 2, 3]
    eager, eager_calls, eager_report, eager_record = _act_ah("eager", obs, seeds, preset)
    captured, captured_calls, captured_report, captured_record = _act_ah("captured", obs, seeds, preset)
    assert eager_record == {"sampler": "eager"}
    assert captured_record == {"sampler": "captured", "cuda_graph": False, "fused_quant": False, "tf32": False}
    # Every AH hook fired on both paths (167 layers, time MLP and AdaRMS modulations included).
    assert eager_report.unfired() == captured_report.unfired() == []
    assert len(captured_report.result.hooks) == 167
    # One flow step: each hook runs once per chunk on both paths, with one row block per episode.
    captured_by_layer = {name: (x, y) for name, x, y in captured_calls}
    assert len(captured_by_layer) == len(captured_calls) == len(eager_calls) == 167
    agreeing = 0
    for b in range(len(obs)):
        if _rel(captured[b], eager[b]) <= REL_TOL:
            agreeing += 1
            continue
        first = next((name, x, y) for name, x, y in eager_calls if _rel(captured_by_layer[name][1][b], y[b]) > REL_TOL)
        name, x, _ = first
        assert _rel(captured_by_layer[name][0][b], x[b]) <= REL_TOL, f"episode {b}: {name} input already differs"
    assert agreeing >= len(obs) // 2  # flips are the exception, not the rule
    assert not np.allclose(captured[0], captured[1])  # the chunks depend on the episode


def test_auto_is_eager_on_the_cpu_and_the_header_records_it(tmp_path):
    cfg = cell_config("libero/libero_spatial/pi05/rtn-W4A4-ah", STUDY)
    assert cfg["runner"]["sampler"] == "auto"
    run = CellRun(cfg, tmp_path, progress=False)
    run.prepare()
    assert run.header["inference"] == {"sampler": "eager"}
    assert run.header["config"]["runner"]["sampler"] == "auto"
    # The choice is part of the cell: forcing a sampler names another folder.
    forced = cell_config(cfg["ref"], {**STUDY, "runner": {**STUDY["runner"], "sampler": "eager"}})
    assert config_hash(forced) != config_hash(cfg)


def test_auto_is_captured_on_cuda_only_where_capture_is_possible():
    cuda = {**STUDY, "runner": {**STUDY["runner"], "device": "cuda"}}
    def sampler(ref: str) -> str:
        return resolve_sampler(CellConfig.from_dict(cell_config(ref, cuda)), adapter_class(ref.split("/")[2]))

    assert sampler("libero/libero_spatial/pi05/rtn-W4A4-e2e") == "captured"
    assert sampler("libero/libero_spatial/pi05/int8-W8-llm") == "eager"
    assert sampler("libero/libero_spatial/pi0/rtn-W4A4-e2e") == "eager"


@pytest.mark.parametrize(
    "ref, reason",
    [
        ("libero/libero_spatial/pi0/rtn-W4A4-ah", "model pi0 has no captured sampler"),
        ("libero/libero_spatial/pi05/int8-W8-llm", "method int8 cannot be captured"),
    ],
)
def test_an_impossible_captured_choice_fails_before_any_episode(tmp_path, ref, reason):
    cfg = cell_config(ref, {**STUDY, "runner": {**STUDY["runner"], "sampler": "captured"}})
    run = CellRun(cfg, tmp_path, progress=False)
    with pytest.raises(UserError, match=rf"study\.runner\.sampler is 'captured' but {reason}"):
        run.prepare()
    assert not any(tmp_path.iterdir())  # nothing was loaded, run or written


def test_an_unknown_sampler_is_named():
    with pytest.raises(UserError, match="study.runner.sampler: 'graph' is not allowed; allowed values: auto, captured, eager"):
        cell_config("libero/libero_spatial/pi05/rtn-W4A4-ah", {**STUDY, "runner": {"sampler": "graph"}})
