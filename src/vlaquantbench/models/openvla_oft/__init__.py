"""OpenVLA-OFT: architecture assembled from its published configuration, and component scopes."""
