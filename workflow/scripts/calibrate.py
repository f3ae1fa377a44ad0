"""Rule calibrate: activation statistics from unquantized rollouts, shared by the cells that use them."""

from vlaquantbench.runner.calibration import calibrate

calibrate(
    snakemake.params.calibration,  # noqa: F821
    snakemake.output[0],  # noqa: F821
    snakemake.input.checkpoint,  # noqa: F821
    **snakemake.config.get("study", {}).get("execution", {}),  # noqa: F821
)
