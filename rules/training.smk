# A policy trained from scratch on the demonstrations (issue 30), on a GPU:
#   snakemake --cores 16 checkpoints/pi05_metaworld/training.json --configfile config/trained_study.yaml
# regenerates the committed checkpoint (rule demonstrations first, if its dataset is missing).
if TRAINING is not None and DEMONSTRATIONS is not None:

    rule train_policy:
        input:
            dataset=rules.demonstrations.output.dataset,
            manifest=rules.demonstrations.output.manifest,
        output:
            # A plain checkpoint folder (vlaquantbench.models.trained_home); training.json is written last.
            policy=directory(f"{TRAINING.output}/policy"),
            tokenizer=directory(f"{TRAINING.output}/tokenizer"),
            provenance=f"{TRAINING.output}/training.json",
        params:
            # The section as a mapping, every default spelled out: Snakemake reruns the training when it
            # changes (a dataclass parameter is one it cannot compare).
            training=TRAINING.as_dict(),
            dataset_repo_id=DEMONSTRATIONS.repo_id,
        log:
            "logs/train_policy.log",
        threads: workflow.cores  # the CPU device's intra-op threads; on a GPU, loading the dataset
        resources:
            gpu=int(TRAINING.device.startswith("cuda")),
        script:
            "../workflow/scripts/train_policy.py"
