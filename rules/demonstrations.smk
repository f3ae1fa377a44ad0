# Scripted-expert demonstrations of the section's benchmark as a LeRobotDataset (issue 30): what the trained
# policy learns from. Only with a `demonstrations` section (config/trained_study.yaml: Meta-World's experts):
#   snakemake --cores 16 results/demonstrations/metaworld/manifest.tsv --configfile config/trained_study.yaml
# One worker process per core the job gets. A config that would evaluate or calibrate on a variation the
# demonstrations may record is refused here, while the DAG is built: every range its study names, whether or
# not its cells are in the DAG, and those of the cells that are (vlaquantbench.demonstrations.overlap).
from vlaquantbench.demonstrations import (  # noqa: E402
    DATASET_DIR,
    MANIFEST_FILE,
    SUMMARY_FILE,
    DemonstrationConfig,
    check_disjoint_from_evaluation,
)

DEMONSTRATIONS = DemonstrationConfig.from_dict(config["demonstrations"]) if "demonstrations" in config else None

if DEMONSTRATIONS is not None:
    check_disjoint_from_evaluation(DEMONSTRATIONS, WF.study, CELLS.values())

    rule demonstrations:
        output:
            dataset=directory(f"{DEMONSTRATIONS.dir}/{DATASET_DIR}"),
            summary=f"{DEMONSTRATIONS.dir}/{SUMMARY_FILE}",
            manifest=f"{DEMONSTRATIONS.dir}/{MANIFEST_FILE}",
        log:
            f"logs/demonstrations/{Path(DEMONSTRATIONS.dir).name}.log",
        benchmark:
            f"logs/demonstrations/{Path(DEMONSTRATIONS.dir).name}.benchmark.tsv"
        threads: workflow.cores
        params:
            config=DEMONSTRATIONS,
        script:
            "../workflow/scripts/demonstrations.py"
