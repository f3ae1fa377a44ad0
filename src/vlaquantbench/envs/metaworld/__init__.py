"""Meta-World (`metaworld` 3.0.0) on lerobot 0.6.1's conventions: suites, seeded task variations,
batched worker envs that render only what a policy reads.

```python
from vlaquantbench.envs.metaworld import MetaWorldSuite, MetaWorldVectorEnv

suite = MetaWorldSuite("metaworld_easy")
with MetaWorldVectorEnv(suite, num_envs=2, camera_size=None) as env:  # None: no image rendered
    obs = env.reset(suite.episodes(episodes_per_task=1, task_ids=[0, 1]))
    obs, success = env.step(actions)  # actions: float[2, 4] in [-1, 1]
```
"""

from vlaquantbench.envs.metaworld.suite import (
    STEP_LIMIT,
    SUITES,
    MetaWorldSuite,
    MetaWorldTask,
    lerobot_metaworld_config,
    suite_task_names,
    variation_seed,
)
from vlaquantbench.envs.metaworld.vector_env import (
    ACTION_DIM,
    CAMERA_SIZE,
    MetaWorldVectorEnv,
    MetaWorldWorkerError,
    simulator_versions,
)

__all__ = [
    "ACTION_DIM",
    "CAMERA_SIZE",
    "STEP_LIMIT",
    "SUITES",
    "MetaWorldSuite",
    "MetaWorldTask",
    "MetaWorldVectorEnv",
    "MetaWorldWorkerError",
    "lerobot_metaworld_config",
    "simulator_versions",
    "suite_task_names",
    "variation_seed",
]
