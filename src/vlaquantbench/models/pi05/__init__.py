"""pi0.5 (lerobot `PI05Pytorch`): component scopes, builders and the runtime adapter."""
