"""Meta-World's scripted experts behind the adapter protocol: each observation's task picks its expert
(lerobot's `TASK_POLICY_MAPPING`), which maps Meta-World's whole state to one action."""

from __future__ import annotations

import importlib.metadata
from collections.abc import Sequence

import numpy as np
import torch
from torch import nn

from vlaquantbench.envs.metaworld import ACTION_DIM, lerobot_metaworld_config
from vlaquantbench.models.adapter import AdapterBase


class MetaWorldExpertAdapter(AdapterBase):
    name = "metaworld_expert"
    # The experts read `environment_state` only: the env need render no image for them.
    reads_images = False

    def load(self) -> None:
        self.model = nn.Module()  # nothing to quantize
        self.predicted_chunk = 1
        self._check_chunk()
        self.checkpoint_provenance = {"policies": "metaworld.policies",
                                      "metaworld": importlib.metadata.version("metaworld")}
        self._experts: dict[str, object] = {}

    def _expert(self, task: str):
        """The task's expert; built once (the experts keep no state between calls)."""
        if task not in self._experts:
            import metaworld.policies

            policy_class = lerobot_metaworld_config()["TASK_POLICY_MAPPING"][task]
            self._experts[task] = getattr(metaworld.policies, policy_class)()
        return self._experts[task]

    def act(self, observations: Sequence[dict], generators: Sequence[torch.Generator]) -> np.ndarray:
        """One action per observation, `[n, 1, 4]`: the experts draw no random numbers."""
        self._start_chunk(observations, generators)
        actions = [self._expert(o["task"]).get_action(o["environment_state"]) for o in observations]
        return np.asarray(actions, dtype=np.float64).reshape(len(observations), 1, ACTION_DIM)


ADAPTER = MetaWorldExpertAdapter
