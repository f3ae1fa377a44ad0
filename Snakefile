# VLAQuantBench workflow: checkpoints -> calibration -> closed-loop rollouts -> records -> tables.
#   snakemake --cores 2 tables/lattice.tex                                   # the trained policy (config/main.yaml)
#   snakemake --cores 2 tables/lattice.tex --configfile config/config.yaml   # random-weight LIBERO demo
#   snakemake tables/lattice.tex --cores 2 --configfile config/reference.yaml # authors' records, no GPU
# (targets before --configfile: Snakemake 9 reads every later word as another config file)
from snakemake.utils import min_version, validate

min_version("9.0")

configfile: "config/config.yaml"


# The main job: with no --configfile, the pi0.5 trained here on Meta-World (config/main.yaml, merged over the
# defaults; --config still wins). Every --configfile is merged over config/config.yaml alone.
if not workflow.overwrite_configfiles:

    configfile: "config/main.yaml"


include: "rules/common.smk"
include: "rules/analysis.smk"
include: "rules/rollout.smk"
include: "rules/replay.smk"
include: "rules/sequential.smk"
include: "rules/search.smk"
include: "rules/demonstrations.smk"
include: "rules/training.smk"


onerror:
    # Each failed job's one-line cause, after Snakemake's report of its inputs and outputs.
    from vlaquantbench.rule_log import failed_job_causes

    causes = failed_job_causes(log)
    if causes:
        print("\nThe run stopped because:\n  " + "\n  ".join(causes), file=sys.stderr)


rule all:
    input:
        expand("tables/{table}.tex", table=config["tables"]),
        "tables/summary.csv",
        [] if WF.manifest else BUILT_MANIFEST,
