"""pi0 (lerobot `PI0Pytorch`): component scopes, builders and the runtime adapter."""
