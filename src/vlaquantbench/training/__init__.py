"""Training a policy from scratch on the demonstrations (rule train_policy): `loop.train_policy`,
on the dataset held on the device (`frames.DeviceFrames`)."""

from vlaquantbench.training.loop import TrainingPaused, train_policy, weights_revision

__all__ = ["TrainingPaused", "train_policy", "weights_revision"]
