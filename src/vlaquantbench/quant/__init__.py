"""Post-training quantization of VLA policies: RTN grids, presets, scoped application with
counting activation hooks, and rollout calibration. See `vlaquantbench.quant.apply`.

Names are imported on first access (PEP 562), so the torch-free parts (`quant.presets`,
`quant.methods`, `quant.subsets`, `quant.patterns`) load without torch when the workflow parses.
"""

import importlib

_EXPORTS = {
    "HooksNotFired": "apply",
    "MethodResult": "apply",
    "QuantConfig": "apply",
    "QuantReport": "apply",
    "quantize_": "apply",
    "register_method": "methods",
    "registered_methods": "methods",
    "CalibrationSettings": "calibration",
    "CalibrationStats": "calibration",
    "Preset": "presets",
    "WeightGrid": "presets",
    "parse_preset": "presets",
    "Selection": "scope",
    "select_layers": "scope",
    "Subset": "subsets",
    "get_subset": "subsets",
    "subsets_for": "subsets",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name not in _EXPORTS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"{__name__}.{_EXPORTS[name]}"), name)
