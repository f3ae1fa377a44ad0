"""Scripted-expert demonstrations of a benchmark, written as a LeRobotDataset (issue 30, item 1).

```python
from vlaquantbench.config import load_yaml
from vlaquantbench.demonstrations import DemonstrationConfig, write_demonstrations

config = DemonstrationConfig.from_dict(load_yaml("config/trained_study.yaml", "config")["demonstrations"])
write_demonstrations(config, config.dir, workers=16)
```

The benchmark's scripted expert (the model its declaration names, `envs.registry.ScriptedExpert`) runs
through the closed-loop runner on the project's own env of that benchmark (the worker, camera, flips and
step limit the closed loop evaluates with), rendering `image_size` pixels. Only successful episodes are
kept; every attempt is counted. See `dataset.py`.
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
