from vlaquantbench.replay.tables import write_replay_table

write_replay_table("all_formats", snakemake.params.analysis_dir, snakemake.output[0], study=snakemake.params.study,
                   success_summary=snakemake.input.success, formats=snakemake.params.formats)
