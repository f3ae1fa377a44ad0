from vlaquantbench.replay.analysis import analyze_files

analyze_files(list(snakemake.input), snakemake.output[0], study=snakemake.params.study)
