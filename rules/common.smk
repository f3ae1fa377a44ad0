# Shared by every rule file: config validation and where a cell's records live.
import sys
from pathlib import Path

sys.path.insert(0, str(Path(workflow.basedir) / "src"))

validate(config, "../workflow/schemas/config.schema.yaml")

from vlaquantbench.workflow import WorkflowConfig  # noqa: E402

WF = WorkflowConfig.from_snakemake(config, workflow.basedir)
