"""X-VLA (lerobot 0.6.1 `XVLAModel`, configured like `2toINF/X-VLA-Libero`): component scopes."""

LABEL = "X-VLA"  # how the paper's tables name the model (`models.registry.model_label`)
