"""pi0.5 (lerobot `PI05Pytorch`): component scopes, builders and the runtime adapter."""

LABEL = r"$\pi_{0.5}$"  # how the paper's tables name the model (`models.registry.model_label`)
