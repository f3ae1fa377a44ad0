"""Variant "random": the full-size architecture with random weights (its build is too heavy for a CPU test;
the GPU closed-loop benchmark runs it)."""

import pytest

from vlaquantbench.errors import UserError
from vlaquantbench.models.adapter import AdapterConfig, make_adapter


def test_random_variant_refuses_an_unsupported_dtype_before_building():
    adapter = make_adapter(AdapterConfig(model="pi05", variant="random", dtype="float16"))
    with pytest.raises(UserError, match="variant 'random' runs in bfloat16 or float32, not 'float16'"):
        adapter.load()
    assert adapter.model is None
