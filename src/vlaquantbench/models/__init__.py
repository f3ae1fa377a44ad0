"""Policy architectures: component scopes and builders (`get_model_spec`) and runtime adapters."""

from vlaquantbench.models.registry import COMPONENT_NAMES, Component, ModelSpec, get_model_spec, model_names

__all__ = ["COMPONENT_NAMES", "Component", "ModelSpec", "get_model_spec", "model_names"]
