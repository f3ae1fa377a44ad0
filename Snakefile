# VLAQuantBench workflow: checkpoints -> calibration -> closed-loop rollouts -> records -> tables.
#   snakemake --cores 2 tables/lattice.tex                                   # demo study (config/config.yaml)
#   snakemake --cores 2 --configfile config/reference.yaml tables/lattice.tex # authors' records, no GPU
from snakemake.utils import min_version, validate

min_version("9.0")

configfile: "config/config.yaml"


include: "rules/common.smk"
include: "rules/analysis.smk"
include: "rules/rollout.smk"
include: "rules/replay.smk"


rule all:
    input:
        expand("tables/{table}.tex", table=config["tables"]),
        "tables/summary.csv",
