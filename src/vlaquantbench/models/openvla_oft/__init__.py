"""OpenVLA-OFT: architecture assembled from its published configuration, and component scopes."""

LABEL = "OpenVLA-OFT"  # how the paper's tables name the model (`models.registry.model_label`)
