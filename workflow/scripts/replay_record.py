from vlaquantbench.replay.record import record_to

record_to(snakemake.params.study, snakemake.params.options, snakemake.output[0], snakemake.log[0])
