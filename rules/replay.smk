# Record -> replay per configuration -> analysis -> replay tables (issue: same-observation replay).
# With `replay_analysis_dir` set (e.g. the authors' files), the tables read its
# `<format>/analysis.json` files; otherwise the DAG records full-precision trajectories in LIBERO,
# replays every configuration on them (one job each; full precision twice, under `fp/`) and
# analyses each format under results/replay/<study>/.
from vlaquantbench.replay.study import RecordSettings, analysis_files, load_study, with_formats  # noqa: E402

REPLAY_STUDY = "pi05_libero_spatial"
REPLAY_OPTIONS = config.get("replay") or {}
REPLAY = with_formats(load_study(REPLAY_STUDY), REPLAY_OPTIONS.get("formats"))
REPLAY_DIR = config.get("replay_analysis_dir") or f"results/replay/{REPLAY_STUDY}"
REPLAY_ANALYSES = [str(path) for path in analysis_files(REPLAY_DIR, REPLAY["formats"]).values()]
# The recording: records.json and one file per (task, init state) trajectory, every one declared.
RECORDING = f"results/replay/{REPLAY_STUDY}/records"
TRAJECTORIES = [f"{RECORDING}/{name}" for name in RecordSettings.from_study(REPLAY, REPLAY_OPTIONS).trajectory_files()]
# Success rates of the matching closed-loop cells (SR column): a summary with the authors' columns.
SUCCESS_SUMMARY = config.get("success_summary") or "tables/summary.csv"


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


def replay_runs(replay_format, suffix):
    """One format's replays (`.json` summaries or `.npz` arrays), full precision's two runs first."""
    return [f"results/replay/{REPLAY_STUDY}/fp/{REPLAY['baseline']}.{suffix}",
            f"results/replay/{REPLAY_STUDY}/fp/{REPLAY['repeat']}.{suffix}",
            *(f"results/replay/{REPLAY_STUDY}/{replay_format}/{name}.{suffix}" for name in REPLAY["configurations"])]


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
        study=REPLAY_STUDY,
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
        study=REPLAY_STUDY,
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
        study=REPLAY_STUDY,
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
        study=REPLAY_STUDY,
        formats=REPLAY["formats"],
    script:
        "../workflow/scripts/replay_formats_figure.py"


# Layer diagnostics -> proxy audit (tab:proxy_audit). With `diagnostics_dir` set (e.g. the authors'
# diagnostics/v2), its files are read; otherwise they are collected under results/diagnostics/ on the
# replay study's full-precision recording (models of that recording only).
from vlaquantbench.diagnostics.proxy_audit import diagnostics_files, load_cohort  # noqa: E402

PROXY_COHORT = load_cohort("proxy_audit")
DIAGNOSTICS_DIR = config.get("diagnostics_dir") or "results/diagnostics"


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


def proxy_audit_diagnostics(wildcards):
    """The cohort's diagnostics files; without diagnostics_dir only the recorded model's can be collected."""
    from vlaquantbench.errors import UserError

    uncollectable = [m for m in PROXY_COHORT["models"] if m != REPLAY["model"]]
    if not config.get("diagnostics_dir") and uncollectable:
        raise UserError(f"tables/proxy_audit.tex needs diagnostics of {', '.join(uncollectable)}, which this DAG "
                        f"cannot collect (it records {REPLAY['model']}); set diagnostics_dir to a folder holding them")
    return [str(path) for path in diagnostics_files(PROXY_COHORT, DIAGNOSTICS_DIR).values()]


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
    script:
        "../workflow/scripts/proxy_audit_table.py"
