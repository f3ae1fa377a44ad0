# Record -> replay per configuration -> analysis -> replay tables (same-observation replay) of the study that
# `replay.study` names (REPLAY_SOURCE; the paper's by default). With `replay_analysis_dir` set (e.g. the authors'
# files), the tables read its `<format>/analysis.json` files; otherwise the DAG records full-precision trajectories
# in the study's benchmark (the images of the cameras it declares, and the state), replays every configuration on
# them (one job each; full precision twice, under `fp/`) and analyses each format under results/replay/<study>/.


wildcard_constraints:
    replay_format="fp|" + "|".join(REPLAY["formats"]),


rule replay_record:
    output:
        records=f"{RECORDING}/records.json",
        trajectories=TRAJECTORIES,
    params:
        study=REPLAY,
        options=REPLAY_OPTIONS,
    log:
        f"logs/replay_record/{REPLAY_STUDY}.log",
    script:
        "../workflow/scripts/replay_record.py"


rule replay_configuration:
    wildcard_constraints:
        config="|".join([REPLAY["baseline"], REPLAY["repeat"], *REPLAY["configurations"]]),
    input:
        records=f"{RECORDING}/records.json",
        trajectories=TRAJECTORIES,
    output:
        summary=f"results/replay/{REPLAY_STUDY}/{{replay_format}}/{{config}}.json",
        arrays=f"results/replay/{REPLAY_STUDY}/{{replay_format}}/{{config}}.npz",
    params:
        study=REPLAY,
        preset=lambda wc: "BASELINE" if wc.replay_format == "fp" else wc.replay_format,
        checkpoint_dir=REPLAY_OPTIONS.get("checkpoint_dir"),
    log:
        f"logs/replay_configuration/{REPLAY_STUDY}/{{replay_format}}/{{config}}.log",
    script:
        "../workflow/scripts/replay_configuration.py"


rule replay_analyze:
    input:
        summaries=lambda wc: replay_runs(wc.replay_format, "json"),
        arrays=lambda wc: replay_runs(wc.replay_format, "npz"),
    output:
        f"results/replay/{REPLAY_STUDY}/{{replay_format}}/analysis.json",
    params:
        study=REPLAY,
    log:
        f"logs/replay_analyze/{REPLAY_STUDY}/{{replay_format}}.log",
    script:
        "../workflow/scripts/replay_analyze.py"


rule replay_composition_table:
    input:
        analyses=REPLAY_ANALYSES,
    output:
        tex="tables/replay_composition.tex",
        html=report("tables/replay_composition.html", caption="../workflow/report/derived.rst", category="Tables",
                    labels={"table": "replay_composition"}),
    log:
        "logs/tables/replay_composition.log",
    params:
        source=lambda wc: f"the replay analysis files in {REPLAY_DIR}",
        study=REPLAY_SOURCE,
        formats=REPLAY["formats"],
    script:
        "../workflow/scripts/replay_composition_table.py"


rule replay_all_formats_table:
    input:
        analyses=REPLAY_ANALYSES,
        success=SUCCESS_SUMMARY,
    output:
        tex="tables/replay_all_formats.tex",
        html=report("tables/replay_all_formats.html", caption="../workflow/report/derived.rst", category="Tables",
                    labels={"table": "replay_all_formats"}),
    log:
        "logs/tables/replay_all_formats.log",
    params:
        source=lambda wc: f"the replay analysis files in {REPLAY_DIR}",
        study=REPLAY_SOURCE,
        formats=REPLAY["formats"],
    script:
        "../workflow/scripts/replay_all_formats_table.py"


rule replay_bias_table:
    input:
        analyses=REPLAY_ANALYSES,
    output:
        tex="tables/replay_bias.tex",
        html=report("tables/replay_bias.html", caption="../workflow/report/derived.rst", category="Tables",
                    labels={"table": "replay_bias"}),
    log:
        "logs/tables/replay_bias.log",
    params:
        source=lambda wc: f"the replay analysis files in {REPLAY_DIR}",
        study=REPLAY_SOURCE,
        formats=REPLAY["formats"],
    script:
        "../workflow/scripts/replay_bias_table.py"


rule replay_formats_figure:
    input:
        analyses=REPLAY_ANALYSES,
    output:
        report("figures/replay_formats.pdf", caption="../workflow/report/derived.rst", category="Figures"),
    log:
        "logs/figures/replay_formats.log",
    params:
        source=lambda wc: f"the replay analysis files in {REPLAY_DIR}",
        study=REPLAY_SOURCE,
        formats=REPLAY["formats"],
    script:
        "../workflow/scripts/replay_formats_figure.py"


# Layer diagnostics -> proxy audit (tab:proxy_audit). With `diagnostics_dir` set (e.g. the authors'
# diagnostics/v2), its files are read; otherwise they are collected under results/diagnostics/ on the
# replay study's full-precision recording (models of that recording only).
rule diagnostics_collect:
    input:
        records=f"{RECORDING}/records.json",
        trajectories=TRAJECTORIES,
    output:
        "results/diagnostics/{model}-{scope}-{preset}.json",
    params:
        checkpoint_dir=REPLAY_OPTIONS.get("checkpoint_dir"),
    log:
        "logs/diagnostics_collect/{model}-{scope}-{preset}.log",
    script:
        "../workflow/scripts/diagnostics_collect.py"


rule proxy_audit_table:
    input:
        diagnostics=proxy_audit_diagnostics,
        success=SUCCESS_SUMMARY,
    output:
        table="tables/proxy_audit.tex",
        scopes="tables/proxy_audit.scopes.csv",
        html=report("tables/proxy_audit.html", caption="../workflow/report/derived.rst", category="Tables",
                    labels={"table": "proxy_audit"}),
    log:
        "logs/tables/proxy_audit.log",
    params:
        source=lambda wc: f"the layer diagnostics in {DIAGNOSTICS_DIR} and the success summary {SUCCESS_SUMMARY}",
        models=list(PROXY_COHORT["models"]),
        cohort=PROXY_COHORT_FILE,
    script:
        "../workflow/scripts/proxy_audit_table.py"
