from vlaquantbench.diagnostics.collect import collect

collect(snakemake.input[0], snakemake.wildcards.model, snakemake.wildcards.scope, snakemake.wildcards.preset,
        snakemake.output[0], checkpoint_dir=snakemake.params.checkpoint_dir, log=snakemake.log[0])
