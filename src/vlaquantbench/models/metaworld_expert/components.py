"""The experts have no network: no component scopes, and an empty module as their architecture, so
that the registry's lookups (layer index, quantization scopes) find nothing to quantize rather than
a model without a spec."""

from torch import nn

from vlaquantbench.models.registry import ModelSpec


def _no_network(device, seed) -> nn.Module:
    return nn.Module()


SPEC = ModelSpec(name="metaworld_expert", components={}, builders={"full": _no_network, "demo": _no_network})
