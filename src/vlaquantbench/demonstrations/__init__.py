"""Scripted-expert demonstrations on Meta-World, written as a LeRobotDataset (issue 30, item 1).

```python
from vlaquantbench.demonstrations import DemonstrationConfig, write_demonstrations

config = DemonstrationConfig.from_dict({"tasks": ["drawer-close-v3", "door-open-v3"], "episodes_per_task": 50})
write_demonstrations(config, "results/demonstrations/metaworld", workers=16)
```

The experts (`models/metaworld_expert`) run through the closed-loop runner on the project's own
Meta-World env (the worker, camera, flips and step limit the closed loop evaluates with), rendering
`image_size` pixels. Only successful episodes are kept; every attempt is counted. See `dataset.py`.
"""

from vlaquantbench.demonstrations.dataset import (
    DATASET_DIR,
    MANIFEST_FILE,
    SUMMARY_FILE,
    DemonstrationConfig,
    write_demonstrations,
)
from vlaquantbench.demonstrations.overlap import check_disjoint_from_evaluation

__all__ = [
    "DATASET_DIR",
    "MANIFEST_FILE",
    "SUMMARY_FILE",
    "DemonstrationConfig",
    "check_disjoint_from_evaluation",
    "write_demonstrations",
]
