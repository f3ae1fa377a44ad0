from vlaquantbench.replay.tables import write_replay_table

write_replay_table("composition", snakemake.params.analysis_dir, snakemake.output[0], study=snakemake.params.study,
                   formats=snakemake.params.formats)
