"""pi0 (lerobot `PI0Pytorch`): component scopes, builders and the runtime adapter."""

LABEL = r"$\pi_0$"  # how the paper's tables name the model (`models.registry.model_label`)
