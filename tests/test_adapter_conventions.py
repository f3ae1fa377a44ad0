"""Adapter conventions (`models/<model>/client.py` ADAPTER_CONVENTIONS) say how a model's client feeds the policy a
benchmark's observations and reads its actions (X-VLA's domain id and wrist view, OFT's gripper sign). They are keyed by
(model, benchmark): a cell of a model on a benchmark its client declares none for is refused by name when its config
resolves, before any job starts, and so is an adapter built for it or driven by hand with that benchmark's observations."""

import numpy as np
import pytest
from demo_study import demo_study

from vlaquantbench.cells import cell_config
from vlaquantbench.errors import UserError
from vlaquantbench.models.adapter import AdapterConfig, make_adapter
from vlaquantbench.models.client import adapter_conventions


@pytest.mark.parametrize("model", ["xvla", "openvla_oft"])
def test_a_cell_on_a_benchmark_without_its_models_conventions_is_refused_naming_both(model):
    ref = f"metaworld/metaworld_mt10/{model}/rtn-BASELINE-e2e"
    with pytest.raises(UserError, match=f"cell '{ref}': model '{model}' has no adapter conventions on benchmark "
                                        "'metaworld': its client.py ADAPTER_CONVENTIONS declares libero"):
        cell_config(ref, demo_study(model))


@pytest.mark.parametrize("model", ["xvla", "openvla_oft"])
def test_an_adapter_for_a_benchmark_without_conventions_is_refused_before_it_loads(model):
    with pytest.raises(UserError, match=f"model '{model}' has no adapter conventions on benchmark 'metaworld'"):
        make_adapter(AdapterConfig(model=model, variant="demo", benchmark="metaworld"))


def test_a_model_declaring_none_feeds_every_benchmark_alike():
    assert adapter_conventions("pi05", "metaworld") is None and adapter_conventions("pi05", "libero") is None


def test_a_policy_driven_by_hand_reads_the_conventions_of_the_benchmark_its_observation_fits():
    adapter = make_adapter(AdapterConfig(model="xvla", variant="demo"))
    frame = np.zeros((8, 8, 3), dtype=np.uint8)
    assert adapter.adapter_conventions({"agentview": frame, "wrist": frame, "state": 0}) == \
        adapter_conventions("xvla", "libero")
    with pytest.raises(UserError, match="model 'xvla' has no adapter conventions on benchmark 'metaworld'"):
        adapter.adapter_conventions({"image": frame, "state": 0})
