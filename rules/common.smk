# Shared by all rule files. It holds the validated config and, one section per rule file, the constants and
# functions its rules take their inputs, outputs, parameters and resources from; rule files hold only rules.
import functools
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(workflow.basedir) / "src"))

validate(config, "../workflow/schemas/config.schema.yaml")

from vlaquantbench import cells as cell_configs  # noqa: E402
from vlaquantbench.diagnostics.proxy_audit import diagnostics_files, load_cohort  # noqa: E402
from vlaquantbench.envs.memory import job_memory_mb  # noqa: E402
from vlaquantbench.records.cell import EPISODES_FILE, HEADER_FILE, JOURNAL_FILE  # noqa: E402
from vlaquantbench.replay.study import RecordSettings, analysis_files, load_study, study_name, with_formats  # noqa: E402
from vlaquantbench.runner.gpus import SLOTS_DIR, LocalGpuPlan, NoGpu  # noqa: E402
from vlaquantbench.runner.lock import LOCK_FILE  # noqa: E402
from vlaquantbench.training.config import TrainingConfig  # noqa: E402
from vlaquantbench.workflow import BUILT_MANIFEST, CELLS_DIR, WorkflowConfig  # noqa: E402

WF = WorkflowConfig.from_snakemake(config, workflow.basedir)


# --- Records, tables and figures (rules/analysis.smk) ---------------------------------------------
PAPER_TABLES = WF.table_names()
FROZEN_MANIFEST = [str(WF.manifest)] if WF.manifest else []


def records_of(refs):
    """Record files of the cells `refs` (authors' .jsonl, a cell folder's episodes.parquet, or the DAG's cell)."""
    return [WF.cell_input(ref) for ref in refs]


def headers_of(refs):
    """The header.json files read beside the cell folders among `refs` (declared inputs too)."""
    return [header for header in map(WF.cell_header, refs) if header is not None]


def report_params(target):
    """What the report's caption of `target` names: its data source and what its records were checked against."""
    return {"target": target, "source": WF.data_source(), "checks": WF.record_checks()}


# --- Cells: checkpoints, calibrations and rollouts (rules/rollout.smk) ----------------------------
# Built (and every cell checked against the registries and the layer-name index) at parse time.
CELLS = {} if WF.records_dir else WF.study_cells()
CALIBRATIONS = {
    cell_configs.config_hash(calib): calib
    for calib in map(cell_configs.calibration_config, CELLS.values())
    if calib is not None
}
# A checkpoint trained here (study.models.<model>.trained) loads from its own folder (`trained_home` of
# cells.checkpoint_request, which `vqb rollout` asks too). Its training.json is read, and the folder verified
# against it, while the DAG is built (the revision it names is hashed into every cell), so it is no job's input:
# a missing one is refused then, naming the command that trains it (rule train_policy). As an input it would
# also rerun the training of a committed checkpoint whose demonstrations are not committed.
CHECKPOINTS = {cell_configs.checkpoint_key(cfg): cell_configs.checkpoint_request(cfg, WF.study) for cfg in CELLS.values()}


def on_gpu(cfg):
    return cfg["runner"]["device"].startswith("cuda")


# Local GPU jobs (no SLURM, whose --gpus=1 isolates each job): Snakemake counts the `gpu` resource but
# gives no job a device, so each takes a slot of its own (vlaquantbench.runner.gpus); `--resources gpu`
# is set to the slot count (devices x study.execution.jobs_per_gpu), refused above it, and the node's
# cores are split between the GPU jobs.
GPU_PLAN = None
NO_GPU = None  # the refusal of a study on cuda on a node without GPUs, which dry runs only state
if workflow.local_exec and "SLURM_JOB_ID" not in os.environ and any(map(on_gpu, [*CELLS.values(), *CALIBRATIONS.values()])):
    requested = workflow.global_resources.get("gpu")
    try:
        GPU_PLAN = LocalGpuPlan.for_node(WF.study.execution.gpus, None if requested is None else requested.value,
                                         workflow.cores, WF.study.execution.jobs_per_gpu)
    except NoGpu as err:
        NO_GPU = err
        print(f"{err}: a real run stops here (a dry run plans the jobs all the same)", file=sys.stderr)
    if GPU_PLAN is not None and workflow.is_main_process:
        workflow.register_resource("gpu", GPU_PLAN.jobs)
        print(GPU_PLAN.describe(WF.study.execution.num_envs), file=sys.stderr)


def gpu_job(cfg):
    """A GPU job's `threads`, its LIBERO workers and its slot, where the workflow assigns its device."""
    if GPU_PLAN is None or not on_gpu(cfg):
        return {"threads": 2, "slots": None}
    return {"threads": GPU_PLAN.threads, "workers": GPU_PLAN.workers(WF.study.execution.num_envs),
            "slots": {"dir": SLOTS_DIR, "gpus": WF.study.execution.gpus, "per_gpu": WF.study.execution.jobs_per_gpu}}


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


# --- Replay and layer diagnostics (rules/replay.smk) ----------------------------------------------
REPLAY_OPTIONS = config.get("replay") or {}
# The replay study (replay.study: the path of its YAML, on any benchmark; default the paper's) and the name its
# folders take (the file's stem).
REPLAY_SOURCE = REPLAY_OPTIONS.get("study") or str(Path(workflow.basedir) / "config/replay/pi05_libero_spatial.yaml")
REPLAY_STUDY = study_name(REPLAY_SOURCE)
REPLAY = with_formats(load_study(REPLAY_SOURCE), REPLAY_OPTIONS.get("formats"))
REPLAY_DIR = config.get("replay_analysis_dir") or f"results/replay/{REPLAY_STUDY}"
REPLAY_ANALYSES = [str(path) for path in analysis_files(REPLAY_DIR, REPLAY["formats"]).values()]
# The recording: records.json and one file per (task, init state) trajectory, every one declared.
RECORDING = f"results/replay/{REPLAY_STUDY}/records"
TRAJECTORIES = [f"{RECORDING}/{name}" for name in RecordSettings.from_study(REPLAY, REPLAY_OPTIONS).trajectory_files()]
# Success rates of the matching closed-loop cells (SR column): a summary with the authors' columns.
SUCCESS_SUMMARY = config.get("success_summary") or "tables/summary.csv"


def replay_runs(replay_format, suffix):
    """One format's replays (`.json` summaries or `.npz` arrays), full precision's two runs first."""
    return [f"results/replay/{REPLAY_STUDY}/fp/{REPLAY['baseline']}.{suffix}",
            f"results/replay/{REPLAY_STUDY}/fp/{REPLAY['repeat']}.{suffix}",
            *(f"results/replay/{REPLAY_STUDY}/{replay_format}/{name}.{suffix}" for name in REPLAY["configurations"])]


# Layer diagnostics -> proxy audit (tab:proxy_audit)
PROXY_COHORT_FILE = str(Path(workflow.basedir) / "config/cohorts/proxy_audit.yaml")  # the paper's cohort
PROXY_COHORT = load_cohort(PROXY_COHORT_FILE)
DIAGNOSTICS_DIR = config.get("diagnostics_dir") or "results/diagnostics"


def proxy_audit_diagnostics(wildcards):
    """The cohort's diagnostics files; without diagnostics_dir only the recorded model's can be collected."""
    from vlaquantbench.errors import UserError

    uncollectable = [m for m in PROXY_COHORT["models"] if m != REPLAY["model"]]
    if not config.get("diagnostics_dir") and uncollectable:
        raise UserError(f"tables/proxy_audit.tex needs diagnostics of {', '.join(uncollectable)}, which this DAG "
                        f"cannot collect (it records {REPLAY['model']}); set diagnostics_dir to a folder holding them")
    return [str(path) for path in diagnostics_files(PROXY_COHORT, DIAGNOSTICS_DIR).values()]


# --- Sequential evaluation (rules/sequential.smk) -------------------------------------------------
SEQUENTIAL = config.get("sequential") or {}
SEQUENTIAL_TABLES = SEQUENTIAL.get("tables", ["clustered", "lattice"])
SEQUENTIAL_TARGET = "tables/sequential.tex"


def sequential_refs():
    """The recorded cells of the listed tables' contrasts (read when the target is asked for: a study whose
    tables_dir lacks those tables builds its DAG without them)."""
    refs = sorted({ref for name in SEQUENTIAL_TABLES for pair in WF.table(name).contrasts() for ref in pair})
    return WF.checked_refs(WF.record_refs(refs, SEQUENTIAL_TARGET), SEQUENTIAL_TARGET)


# --- Precision search (rules/search.smk) ----------------------------------------------------------
SEARCH = config.get("search") or {}
SEARCH_TARGET = "tables/search.csv"
SEARCH_CHOSEN = "tables/search_chosen.yaml"  # vlaquantbench.tables.search.CHOSEN_FILE
SEARCH_CONFIRM = SEARCH.get("confirm") or {}
CONFIRM_MANIFEST = [SEARCH_CONFIRM["manifest"]] if SEARCH_CONFIRM.get("manifest") else []


def search_cells():
    """The baseline, the candidates with records and the whole space of the search (read when the target is asked
    for). From `records_dir` a candidate without records is no input: the search runs over the whole space and
    answers only when the recorded candidates determine it (vlaquantbench.search), else it refuses naming those
    it needs; the baseline must be recorded."""
    baseline, space = WF.search_space()
    live = WF.study.sequential
    if WF.records_dir is None and live is not None:  # the DAG runs the candidates under the live rule
        from vlaquantbench.search import SearchDesign, check_live_design

        check_live_design(SearchDesign(SEARCH.get("alpha", 0.05), SEARCH.get("margin_pp", 5.0)), len(space) - 1,
                          baseline, live.alpha, live.margin_pp, live.against)
    present = [baseline, *(ref for ref in WF.recorded(space) if ref != baseline)]
    return baseline, WF.checked_refs(WF.record_refs(present, SEARCH_TARGET), SEARCH_TARGET), space


@functools.cache
def search_ranks():
    """Config hash -> rule rollout's priority for the cells of the search space (search_priority); none where the
    `search` section or its table cannot name a space (the target tables/search.csv refuses it, naming why)."""
    from vlaquantbench.errors import UserError
    from vlaquantbench.search import Candidate, search_order

    try:
        baseline, space = WF.search_space()
        order = search_order(Candidate.from_ref(ref) for ref in space if ref != baseline)
    except UserError:
        return {}
    ranks = {candidate.ref: len(order) - rank for rank, candidate in enumerate(order)}
    ranks[baseline] = len(order) + 1
    return {key: ranks[cfg["ref"]] for key, cfg in CELLS.items() if cfg["ref"] in ranks}


def search_priority(cell):
    """Rule rollout's priority for the cell of config hash `cell`: a candidate of the search space (`search` in the
    config, cells run by this DAG) by its place in the search's order (vlaquantbench.search.search_order: cheapest
    weight memory first; the proxies the headers will give are unknown before any episode, so ties that only
    a proxy would break go by name, as the search orders candidates without one), the cheapest highest and the
    baseline above them all; every other cell 0. A run cut short has thus finished the cheapest candidates, the
    ones the search reads first."""
    if not SEARCH or WF.records_dir is not None:
        return 0
    return search_ranks().get(cell, 0)


def search_held_out():
    """The confirmation's records (search.confirm): the run-seed cells of the space in its records_dir, by
    reference; which one the search chooses is known only when it has run."""
    from vlaquantbench.errors import UserError
    from vlaquantbench.records import find_cells
    from vlaquantbench.tables.search import held_out

    confirm = SEARCH_CONFIRM
    if not confirm:
        return {}
    _, _, space = search_cells()
    if not Path(confirm["records_dir"]).is_dir():
        raise UserError(f"search.confirm.records_dir {confirm['records_dir']} is not a folder: record the chosen cell "
                        f"and the baseline on run seed {confirm['seed']} there first (vqb rollout seed{confirm['seed']}-<cell>)")
    found = find_cells(confirm["records_dir"])
    wanted = {held_out(ref, confirm["seed"]) for ref in space}
    return {ref: str(path) for ref, path in found.items() if ref in wanted}


# --- Training (rules/training.smk) ----------------------------------------------------------------
# The typed `training` section, built once here: an unknown or ill-typed field is refused while the DAG is
# built, naming it.
TRAINING = TrainingConfig.from_dict(config["training"]) if "training" in config else None
