# A policy trained from scratch on the demonstrations (issue 30): `snakemake --cores N <training.output>/training.json
# --configfile config/trained_study.yaml` on a GPU machine regenerates the committed checkpoint.
if "training" in config:
    TRAINING = config["training"]

    rule train_policy:
        input:
            dataset=TRAINING["dataset"] + "/meta/info.json",
            manifest=TRAINING["dataset_manifest"],
        output:
            hub=directory(TRAINING["output"] + "/hub"),
            provenance=TRAINING["output"] + "/training.json",
        params:
            training=TRAINING,
        log:
            "logs/train_policy.log",
        threads: max(1, TRAINING["num_workers"])
        resources:
            gpu=int(TRAINING["device"].startswith("cuda")),
        script:
            "../workflow/scripts/train_policy.py"
