"""Training a policy from scratch on the demonstrations (rule train_policy): `loop.train_policy`,
on the dataset held on the device (`frames.DeviceFrames`), as the typed `training` section says
(`config.TrainingConfig`); `loop.checkpoint_from_saved_state` ends a paused run where its saved state stands."""

from vlaquantbench.training.config import TrainingConfig
from vlaquantbench.training.loop import TrainingPaused, checkpoint_from_saved_state, train_policy, weights_revision

__all__ = ["TrainingConfig", "TrainingPaused", "checkpoint_from_saved_state", "train_policy", "weights_revision"]
