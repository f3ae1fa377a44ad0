from vlaquantbench.replay.figure import write_replay_figure

write_replay_figure(snakemake.params.analysis_dir, snakemake.output[0], study=snakemake.params.study,
                    formats=snakemake.params.formats)
