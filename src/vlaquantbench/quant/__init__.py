"""Post-training quantization of VLA policies: RTN grids, presets, scoped application with
counting activation hooks, and rollout calibration. See `vlaquantbench.quant.apply`."""

from vlaquantbench.quant import kernels  # noqa: F401  (registers the real-kernel and AWQ methods)
from vlaquantbench.quant.apply import (
    HooksNotFired,
    MethodResult,
    QuantConfig,
    QuantReport,
    quantize_,
    register_method,
    registered_methods,
)
from vlaquantbench.quant.calibration import CalibrationSettings, CalibrationStats
from vlaquantbench.quant.presets import Preset, WeightGrid, parse_preset
from vlaquantbench.quant.scope import Selection, select_layers
from vlaquantbench.quant.subsets import Subset, get_subset, subsets_for

__all__ = [
    "CalibrationSettings",
    "CalibrationStats",
    "HooksNotFired",
    "MethodResult",
    "Preset",
    "QuantConfig",
    "QuantReport",
    "Selection",
    "Subset",
    "WeightGrid",
    "get_subset",
    "parse_preset",
    "quantize_",
    "register_method",
    "registered_methods",
    "select_layers",
    "subsets_for",
]
