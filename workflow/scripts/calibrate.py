"""Rule calibrate: activation statistics from unquantized rollouts, shared by the cells that use them."""
# snakemake is injected by Snakemake's script directive.
# ruff: noqa: F821

from vlaquantbench.cells import CalibrationConfig
from vlaquantbench.runner.calibration import calibrate
from vlaquantbench.runner.gpus import job_gpu
from vlaquantbench.rule_log import job_log

with job_log(snakemake), job_gpu(snakemake.params.gpu_slots, f"calibrate {snakemake.wildcards.calibration}"):
    calibrate(CalibrationConfig.from_dict(snakemake.params.calibration), snakemake.output[0], snakemake.input.checkpoint, **snakemake.params.execution)
