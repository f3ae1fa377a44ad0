"""Post-training quantization of VLA policies: RTN grids, presets, scoped application with
counting activation hooks, and rollout calibration. See `vlaquantbench.quant.apply`.

Names are imported on first access (PEP 562), so the torch-free parts (`quant.presets`,
`quant.methods`, `quant.subsets`, `quant.patterns`) load without torch when the workflow parses.
"""

from vlaquantbench.lazy_exports import lazy_exports

_EXPORTS = {
    "apply": ["HooksNotFired", "MethodResult", "QuantConfig", "QuantReport", "quantize_"],
    "methods": ["register_method", "registered_methods"],
    "calibration": ["CalibrationSettings", "CalibrationStats"],
    "presets": ["Preset", "WeightGrid", "parse_preset"],
    "scope": ["Selection", "select_layers"],
    "subsets": ["Subset", "get_subset", "subsets_for"],
}

__all__ = sorted(name for names in _EXPORTS.values() for name in names)
__getattr__ = lazy_exports(__name__, _EXPORTS)
