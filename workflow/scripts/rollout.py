"""Rule rollout: one cell's closed-loop episodes -> header.json + episodes.parquet (resumes its journal)."""

from vlaquantbench.runner.cell import run_cell

run_cell(
    snakemake.params.cell,  # noqa: F821
    snakemake.output.episodes.rsplit("/", 1)[0],  # noqa: F821
    snakemake.input.checkpoint,  # noqa: F821
    snakemake.input.calibration[0] if snakemake.input.calibration else None,  # noqa: F821
    **snakemake.config.get("study", {}).get("execution", {}),  # noqa: F821
)
