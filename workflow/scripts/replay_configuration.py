from vlaquantbench.replay.configuration import replay_to

replay_to(snakemake.input[0], snakemake.params.study, snakemake.wildcards.config, snakemake.params.preset,
          snakemake.output.summary, snakemake.params.checkpoint_dir, snakemake.log[0])
