"""LIBERO on the authors' protocol, offline: suites, official init states, batched worker envs.

```python
from vlaquantbench.envs.libero import LiberoSuite, LiberoVectorEnv

suite = LiberoSuite("libero_spatial")
with LiberoVectorEnv(suite, num_envs=2, camera_size=256) as env:
    obs = env.reset(suite.episodes(episodes_per_task=1, task_ids=[0, 1]))
    obs, success = env.step(actions)  # actions: float[2, 7]
```
"""

from vlaquantbench.envs.libero.offline import assets_dir, cache_dir, config_dir, load_libero
from vlaquantbench.envs.libero.suite import (
    SUITES,
    TASK_SEED_STRIDE,
    EpisodeSpec,
    LiberoSuite,
    LiberoTask,
    all_instructions,
    episode_seed,
)
from vlaquantbench.envs.libero.vector_env import (
    CAMERA_SIZE,
    SETTLE_STEPS,
    LiberoVectorEnv,
    LiberoWorkerError,
    SlotReply,
)
from vlaquantbench.envs.libero.versions import PINNED_MUJOCO, simulator_versions

__all__ = [
    "CAMERA_SIZE",
    "PINNED_MUJOCO",
    "SETTLE_STEPS",
    "SUITES",
    "TASK_SEED_STRIDE",
    "EpisodeSpec",
    "LiberoSuite",
    "LiberoTask",
    "LiberoVectorEnv",
    "LiberoWorkerError",
    "SlotReply",
    "assets_dir",
    "cache_dir",
    "config_dir",
    "episode_seed",
    "load_libero",
    "simulator_versions",
]
