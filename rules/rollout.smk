# Checkpoint -> calibration statistics -> closed-loop rollout per cell (issue: closed-loop LIBERO rollouts).
# The table definitions decide which cells are needed (WF.cell_refs); each cell's canonical config
# (vlaquantbench.cells) names its folder results/cells/<config-hash>/, so a cell reruns exactly
# when something that changes its episodes changes. Without `records_dir` only.
import os  # noqa: E402

from vlaquantbench import cells as cell_configs  # noqa: E402
from vlaquantbench.records.cell import EPISODES_FILE, HEADER_FILE, JOURNAL_FILE  # noqa: E402
from vlaquantbench.envs.memory import job_memory_mb  # noqa: E402
from vlaquantbench.runner.gpus import SLOTS_DIR, LocalGpuPlan, NoGpu  # noqa: E402
from vlaquantbench.runner.lock import LOCK_FILE  # noqa: E402
from vlaquantbench.workflow import CELLS_DIR  # noqa: E402

# Built (and every cell checked against the registries and the layer-name index) at parse time.
CELLS = {} if WF.records_dir else WF.study_cells()
CALIBRATIONS = {
    cell_configs.config_hash(calib): calib
    for calib in map(cell_configs.calibration_config, CELLS.values())
    if calib is not None
}
CHECKPOINTS = {
    cell_configs.checkpoint_key(cfg): {k: cfg[k] for k in ("model", "variant", "checkpoint", "revision")}
    for cfg in CELLS.values()
}
# A checkpoint trained here (study.models.<model>.trained) resolves offline from its own HF_HOME folder. Its
# training.json is read while the DAG is built (the revision it names is hashed into every cell), so it is no
# job's input: a missing one is refused then, naming the command that trains it (rule train_policy). As an input
# it would also rerun the training of a committed checkpoint whose demonstrations are not committed.
for info in CHECKPOINTS.values():
    if WF.study.models[info["model"]].trained:
        info["hf_home"] = WF.study.models[info["model"]].trained


def on_gpu(cfg):
    return cfg["runner"]["device"].startswith("cuda")


# Local GPU jobs (no SLURM, whose --gpus=1 isolates each job): Snakemake counts the `gpu` resource but
# gives no job a device, so each takes a slot of its own (vlaquantbench.runner.gpus); `--resources gpu`
# is set to the device count, refused above it, and the node's cores are split between the GPU jobs.
GPU_PLAN = None
NO_GPU = None  # the refusal of a study on cuda on a node without GPUs, which dry runs only state
if workflow.local_exec and "SLURM_JOB_ID" not in os.environ and any(map(on_gpu, [*CELLS.values(), *CALIBRATIONS.values()])):
    requested = workflow.global_resources.get("gpu")
    try:
        GPU_PLAN = LocalGpuPlan.for_node(WF.study.execution.gpus, None if requested is None else requested.value,
                                         workflow.cores)
    except NoGpu as err:
        NO_GPU = err
        print(f"{err}: a real run stops here (a dry run plans the jobs all the same)", file=sys.stderr)
    if GPU_PLAN is not None and workflow.is_main_process:
        workflow.register_resource("gpu", GPU_PLAN.jobs)
        print(GPU_PLAN.describe(WF.study.execution.num_envs), file=sys.stderr)


onstart:  # a real run, not a dry run
    if NO_GPU is not None:
        raise NO_GPU

def gpu_job(cfg):
    """A GPU job's `threads`, its LIBERO workers and its slot, where the workflow assigns its device."""
    if GPU_PLAN is None or not on_gpu(cfg):
        return {"threads": 2, "slots": None}
    return {"threads": GPU_PLAN.threads, "workers": GPU_PLAN.workers(WF.study.execution.num_envs),
            "slots": {"dir": SLOTS_DIR, "gpus": WF.study.execution.gpus}}


def execution(cfg, kwargs):
    job = gpu_job(cfg)
    return {**kwargs, "num_envs": job["workers"]} if "workers" in job else kwargs


def checkpoint_stamp(cfg):
    return f"results/checkpoints/{cell_configs.checkpoint_key(cfg)}/checkpoint.json"


def memory_mb(cfg, episodes):
    """A job's `mem_mb`: the LIBERO workers it starts (study.execution.num_envs, at most one per episode) at
    their measured footprint, and its policy (vlaquantbench.envs.memory). A profile's set-resources overrides it."""
    workers = gpu_job(cfg).get("workers", WF.study.execution.num_envs)  # fewer on a node's split cores
    return job_memory_mb(cfg["benchmark"], cfg["suite"], min(workers, episodes))


def against_records(cfg):
    """The records (episodes first, then header) of the cell a sequential cell is tested against
    (study.sequential): they exist before its rollout starts."""
    against = (cfg.get("sequential") or {}).get("against")
    return [] if against is None else [f"{CELLS_DIR}/{against['config_hash']}/{name}" for name in (EPISODES_FILE, HEADER_FILE)]


def calibration_stats(cfg):
    calib = cell_configs.calibration_config(cfg)
    return [] if calib is None else [f"results/calibration/{cell_configs.config_hash(calib)}.pt"]


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
        gpu=lambda wc: int(CALIBRATIONS[wc.calibration]["runner"]["device"].startswith("cuda")),
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
    resources:
        gpu=lambda wc: int(CELLS[wc.cell]["runner"]["device"].startswith("cuda")),
        mem_mb=lambda wc: memory_mb(CELLS[wc.cell], len(CELLS[wc.cell]["tasks"]) * CELLS[wc.cell]["episodes_per_task"]),
    script:
        "../workflow/scripts/rollout.py"
