# Checkpoint -> calibration statistics -> closed-loop rollout per cell (issue: closed-loop LIBERO rollouts).
# The table definitions decide which cells are needed (WF.cell_refs); each cell's canonical config
# (vlaquantbench.cells) names its folder results/cells/<config-hash>/, so a cell reruns exactly
# when something that changes its episodes changes. Without `records_dir` only.


onstart:  # a real run, not a dry run
    if NO_GPU is not None:
        raise NO_GPU


rule download_checkpoint:
    output:
        "results/checkpoints/{checkpoint}/checkpoint.json",
    wildcard_constraints:
        checkpoint="|".join(CHECKPOINTS) or "^$",
    params:
        info=lambda wc: CHECKPOINTS[wc.checkpoint],
    log:
        "logs/download_checkpoint/{checkpoint}.log",
    script:
        "../workflow/scripts/download_checkpoint.py"


rule calibrate:
    input:
        checkpoint=lambda wc: checkpoint_stamp(CALIBRATIONS[wc.calibration]),
    output:
        "results/calibration/{calibration}.pt",
    wildcard_constraints:
        calibration="|".join(CALIBRATIONS) or "^$",
    params:
        calibration=lambda wc: CALIBRATIONS[wc.calibration],
        execution=lambda wc: execution(CALIBRATIONS[wc.calibration], WF.study.execution.calibration_kwargs()),
        gpu_slots=lambda wc: gpu_job(CALIBRATIONS[wc.calibration])["slots"],
    log:
        "logs/calibrate/{calibration}.log",
    threads: lambda wc: gpu_job(CALIBRATIONS[wc.calibration])["threads"]
    resources:
        gpu=lambda wc: int(on_gpu(CALIBRATIONS[wc.calibration])),
        mem_mb=lambda wc: memory_mb(CALIBRATIONS[wc.calibration], len(CALIBRATIONS[wc.calibration]["calibration"]["tasks"])
                                    * len(CALIBRATIONS[wc.calibration]["calibration"]["init_states"])),
    script:
        "../workflow/scripts/calibrate.py"


rule rollout:
    input:
        checkpoint=lambda wc: checkpoint_stamp(CELLS[wc.cell]),
        calibration=lambda wc: calibration_stats(CELLS[wc.cell]),
        against=lambda wc: against_records(CELLS[wc.cell]),
    output:
        episodes=f"{CELLS_DIR}/{{cell}}/{EPISODES_FILE}",
        header=f"{CELLS_DIR}/{{cell}}/{HEADER_FILE}",
    wildcard_constraints:
        cell="|".join(CELLS) or "^$",
    # `state`: files the job keeps across failures, declared here because no Snakemake declaration
    # survives one (a failed job's outputs are removed, logs are removed when a job starts, and
    # update() outputs are rolled back). The journal of finished episodes lets a killed cell resume;
    # the writer lock refuses a second job of the cell (another Snakemake, another SLURM job) while one runs.
    params:
        cell=lambda wc: CELLS[wc.cell],
        execution=lambda wc: execution(CELLS[wc.cell], WF.study.execution.as_kwargs()),
        gpu_slots=lambda wc: gpu_job(CELLS[wc.cell])["slots"],
        state=lambda wc: {"journal": f"{CELLS_DIR}/{wc.cell}/{JOURNAL_FILE}", "lock": f"{CELLS_DIR}/{wc.cell}/{LOCK_FILE}"},
    log:
        "logs/rollout/{cell}.log",
    threads: lambda wc: gpu_job(CELLS[wc.cell])["threads"]
    # A precision search's candidates start in the search's order, cheapest first (search_priority): the
    # scheduler starts the ready job of highest priority first.
    priority: lambda wc: search_priority(wc.cell)
    resources:
        gpu=lambda wc: int(on_gpu(CELLS[wc.cell])),
        mem_mb=lambda wc: memory_mb(CELLS[wc.cell], len(CELLS[wc.cell]["tasks"]) * CELLS[wc.cell]["episodes_per_task"]),
    script:
        "../workflow/scripts/rollout.py"
