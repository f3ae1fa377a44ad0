"""Run one cell: load the policy, quantize it, run the missing episodes, check, write the records.

    run = CellRun(cell, out_dir, checkpoint_stamp, calibration_stats, config_hash=...)
    run.start_env() # optional: the simulator workers start while the policy loads
    run.prepare()   # load + quantize; the header is known from here on
    run.run()       # journal-backed episodes; header.json + episodes.parquet when all exist

The protocol checks of the paper (Sec. 5) are enforced here: the adapter must execute the cell's
chunk length, every selected activation hook must have fired, and the MuJoCo pin is checked when
the simulator versions are read. Records are only written when every configured episode exists;
until then they live in the journal, which survives any kill. The suite, its episode specs, the step
limit and the simulator workers come from the benchmark's seam (`vlaquantbench.envs`: `make_suite`,
`make_env`), whatever the benchmark. `run_cell` starts the simulator workers, which build the envs of the first episodes to run, in a thread while `prepare` loads the policy:
both take seconds of CPU, each mostly on one core. One process at a time writes a cell: `run_cell`
(and `run`) hold the cell's writer lock (`runner.lock`), so a second writer is refused by name
before it loads anything.
"""

from __future__ import annotations

import fnmatch
import itertools
import sys
import threading
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

import torch
from tqdm import tqdm

from vlaquantbench.cells import CalibrationConfig, CellCalibration, CellConfig, canonical, quantizer_method
from vlaquantbench.config.study import ExecutionConfig
from vlaquantbench.envs import env_settings, make_env, make_suite, simulator_versions
from vlaquantbench.envs.memory import affordable_workers
from vlaquantbench.errors import UserError
from vlaquantbench.models.adapter import AdapterConfig
from vlaquantbench.models.client import environment_name
from vlaquantbench.models.registry import adapter_class
from vlaquantbench.records import write_cell
from vlaquantbench.records.cell import JOURNAL_FILE
from vlaquantbench.runner.checkpoint import CheckpointStamp
from vlaquantbench.runner.gpus import device_record
from vlaquantbench.runner.journal import EPISODE_KEY, CellJournal, journal_episodes, recorded_keys
from vlaquantbench.runner.lock import writing
from vlaquantbench.runner.loop import run_episodes
from vlaquantbench.quant.apply import hook_summary
from vlaquantbench.quant.semantics import QUANT_SEMANTICS
from vlaquantbench.runner.provenance import code_revision, host, versions
from vlaquantbench.runner.stopping import StoppingRule
from vlaquantbench.software_env import Environment, activate


class CellFailed(UserError):
    """A protocol check failed; the cell's records are not written (its journal is kept)."""


def load_policy(cfg: CellConfig | CalibrationConfig, stamp: CheckpointStamp | None, policy_class: type):
    """The adapter of `policy_class` (the model's, looked up once by the caller) with the policy of `cfg`
    loaded from its checkpoint `stamp` (None: the cell's own weights, e.g. random ones), after checking its
    executed chunk length and controller mode."""
    adapter = policy_class(AdapterConfig.from_cell(cfg, stamp.path if stamp is not None else None, policy_class))
    adapter.load()
    expected = cfg.runner.executed_chunk
    if adapter.executed_chunk != expected:
        raise CellFailed(
            f"{cfg.name}: adapter executes {adapter.executed_chunk} actions per chunk but the cell config "
            f"says {expected} (predicted {adapter.predicted_chunk})"
        )
    mode = getattr(cfg.env, "control_mode", None)  # None: the cell's benchmark has no controller mode to set
    if mode is not None and adapter.control_mode != mode:
        raise CellFailed(
            f"{cfg.name}: the policy's actions are {adapter.control_mode} end-effector poses but the "
            f"cell config runs the simulator's controller in {mode!r} mode"
        )
    return adapter


def calibration_settings(settings: CellCalibration, adapter):
    """The quantizer's calibration settings for a cell's `calibration` config and this model
    (`CalibrationSettings.for_cell`: which components each kind of statistic covers)."""
    from vlaquantbench.quant import CalibrationSettings

    return CalibrationSettings.for_cell(settings, getattr(adapter, "calibrated_components", settings.components))


EPISODE_ORDERS = ("task_major", "interleaved")


def episode_keys(tasks: list[int], episodes_per_task: int, order: str) -> list[tuple[int, int]]:
    """(task, episode) in the order a cell runs them: task by task, or `interleaved` round-robin over tasks
    (round k is episode k of every task). Only the order changes: each episode keeps its identity."""
    if order not in EPISODE_ORDERS:
        raise UserError(f"study.execution.episode_order: {order!r} is not one of {', '.join(EPISODE_ORDERS)}")
    if order == "interleaved":
        return [(task, episode) for episode in range(episodes_per_task) for task in tasks]
    return [(task, episode) for task in tasks for episode in range(episodes_per_task)]


class CellRun:
    """One cell's run. `cfg` is its typed config (a canonical dict is read into one); `config_hash` the hash
    the DAG (or `vqb rollout`) named its folder with, recorded as is (computed from `cfg` only when a caller
    outside the DAG gives none)."""

    def __init__(
        self,
        cfg: CellConfig | dict[str, Any],
        out_dir: str | Path,
        checkpoint_stamp: str | Path | None = None,
        calibration_stats: str | Path | None = None,
        *,
        config_hash: str | None = None,
        journal: str | Path | None = None,
        num_envs: int = ExecutionConfig.num_envs,
        torch_threads: int | None = ExecutionConfig.torch_threads,
        progress: bool = ExecutionConfig.progress,
        episode_order: str = ExecutionConfig.episode_order,
        against_records: str | Path | None = None,
    ):
        self.cfg = cfg = cfg if isinstance(cfg, CellConfig) else CellConfig.from_dict(cfg)
        self.config_hash = config_hash or cfg.config_hash
        self.policy_class = adapter_class(cfg.model)
        self.out_dir = Path(out_dir)
        self.journal = Path(journal) if journal else self.out_dir / JOURNAL_FILE  # default: beside the records
        # Read (and checked) once, before anything loads.
        self.checkpoint = CheckpointStamp.read(checkpoint_stamp) if checkpoint_stamp is not None else None
        self.calibration_stats = calibration_stats
        self.num_envs = num_envs
        self.progress = progress
        self.environment = Environment(environment_name(cfg.model))
        activate(self.environment)  # before anything imports MuJoCo: the simulator and its workers run on its pin
        if torch_threads:
            torch.set_num_threads(torch_threads)
        # study.sequential: the test against the `against` cell's records, read before anything loads; the
        # rule reads whole task-interleaved rounds, so the cell runs in that order.
        self.stopping = StoppingRule(cfg, against_records) if cfg.sequential else None
        if self.stopping is not None:
            episode_order = "interleaved"
        self.suite = make_suite(cfg.benchmark, cfg.suite)
        self.specs = [self.suite.episode_spec(t, e, cfg.seed)
                      for t, e in episode_keys(list(cfg.tasks), cfg.episodes_per_task, episode_order)]
        self.max_steps = cfg.runner.max_steps  # the model's limit on the suite unless the study set one (DAG time)
        self._env: Future | None = None  # the simulator workers, once started
        self._closing = threading.Event()  # set by close_env: a start-up in progress ends early

    def writing(self):
        """The cell's writer lock (re-entrant within this process); CellLocked if another holds it."""
        return writing(self.out_dir, self.journal, self.cfg.ref)

    def start_env(self) -> None:
        """Start the simulator workers for the episodes the journal lacks, in a thread that also builds
        each slot's first env, so that `prepare` loads the policy meanwhile; `run` uses them (or
        starts its own), and `close_env` stops them. The journal is read unchecked here: `run`
        verifies its header before any episode runs."""
        missing = [s for s in self.specs if _key(s) not in recorded_keys(self.journal)]
        if self.stopping is not None:  # the first batch only: none where the journal already holds the decision
            missing = self.stopping.next_batch(journal_episodes(self.journal), missing, self.num_envs)
        self._env = self._start_env(missing)

    def _start_env(self, missing: list) -> Future | None:
        if not missing:
            return None
        benchmark = self.cfg.benchmark
        # Before any worker starts: as many as the memory holds (a warning names both numbers).
        num_envs = affordable_workers(max(1, min(self.num_envs, len(missing))), benchmark, self.cfg.suite,
                                      "study.execution.num_envs")
        # The adapter's class says whether the policy reads images (its instance is still loading).
        settings = env_settings(self.cfg.env, self.policy_class.reads_images)

        def start():
            env = make_env(benchmark, self.suite, num_envs, **settings)
            try:
                if not closing.is_set():  # a cell stopped during its start-up skips building the envs
                    env.preload([spec.task_id for spec in missing[:num_envs]])
            except BaseException:
                env.close()
                raise
            return env

        closing = self._closing = threading.Event()
        pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="env-start")
        future = pool.submit(start)
        pool.shutdown(wait=False)
        return future

    def close_env(self) -> None:
        """Stop the simulator workers, waiting for a start-up in progress to end first (without its env
        builds: Ctrl-C or SIGTERM during the policy's load stops the workers once they have started)."""
        if self._env is not None:
            self._closing.set()
            future, self._env = self._env, None
            try:
                future.result().close()
            except Exception:  # a start-up failure is moot once the cell has failed otherwise
                pass

    def prepare(self) -> None:
        from vlaquantbench.quant import QuantConfig, quantize_
        from vlaquantbench.quant.scope import Selection

        cfg = self.cfg
        # None: a benchmark that declares no MuJoCo pin runs on the software environment's
        self.simulator = simulator_versions(cfg.benchmark, pinned=getattr(cfg.env, "mujoco", None))
        self.adapter = load_policy(cfg, self.checkpoint, self.policy_class)
        calibration, stats = self._calibration()
        quant = QuantConfig.from_preset(
            cfg.preset,
            scope=cfg.scope,
            only=None if cfg.only is None else list(cfg.only),
            exclude=None if cfg.exclude is None else list(cfg.exclude),
            method=quantizer_method(cfg.method),
            calibration=calibration,
            stats=stats,
        )
        # A policy without a network (Meta-World's scripted experts) has no layer to select: its cells are
        # BASELINE cells only (`cells.CellConfig.from_ref`).
        selection = quant.select(self.adapter.model, self.adapter.components) if self.adapter.components else Selection({})
        self.report = quantize_(self.adapter.model, quant, selection)
        quantized = self.report.to_header()
        inference = self.adapter.prepare_inference(self.report)
        if (probe := self.adapter.fast_path_probe()) is not None:
            self.report.reset_hook_calls()  # the probe's chunk is no evidence that the episodes quantized
            inference = {**inference, "fast_path_probe": probe}
            if not probe["passed"]:
                raise CellFailed(f"cell {cfg.ref}: the fast path's first chunk differs from the eager policy's "
                                 f"beyond its bound (fast_path_probe: {probe}); run it with study.runner.sampler: eager")
        # The CUDA device the cell runs on (index, name, UUID); none on the CPU, whose headers stay as they were.
        device = device_record(cfg.runner.device)
        config = cfg.to_dict()  # the canonical form: what the hash covers, in the header as the journal's copy of it
        # JSON round trip: the header compares equal to the journal's copy of it on a rerun.
        self.header = canonical({
            "config_hash": self.config_hash,
            "ref": cfg.ref,
            "cell": cfg.cell,
            **{k: config[k] for k in ("model", "checkpoint", "revision", "benchmark", "suite", "preset", "scope")},
            **{k: config[k] for k in ("only", "exclude", "method", "seed", "episodes_per_task", "calibration")},
            "variant": cfg.variant,
            # What really ran (the config's checkpoint of a random-weight variant names only its architecture).
            **dict(zip(("checkpoint", "revision"), self.adapter.config.weights_ran)),
            # The model's released client conventions and every value this cell sets differently.
            "client": cfg.client.as_dict(),
            "overrides": cfg.overrides.as_dict(),
            **{k: getattr(self.adapter, "checkpoint_provenance", {}).get(k) for k in ("tokenizer", "normalization", "widths")},
            "config": config,
            "quant_report": quantized["quant_report"],
            "quant_format": quantized["quant_format"],
            "selected_layers": quantized["selected_layers"],
            "hooks": {"selected": len(self.report.result.hooks)},
            "chunk": {"predicted": self.adapter.predicted_chunk, "executed": self.adapter.executed_chunk},
            "inference": inference,
            "max_steps": self.max_steps,
            "versions": {**versions(), **{k: v for k, v in self.simulator.items() if k != "mujoco"}},
            "environment": self.environment.describe(),
            "host": host(),
            "quant_semantics": QUANT_SEMANTICS,
            "code_revision": code_revision(),
            **({} if device is None else {"device": device}),
        })

    def _calibration(self):
        settings = self.cfg.calibration
        if settings is None:
            return None, None
        from vlaquantbench.quant.calibration import load_stats

        if self.calibration_stats is None:
            raise UserError(f"cell {self.cfg.ref} is calibrated but no calibration statistics were given")
        return calibration_settings(settings, self.adapter), load_stats(self.calibration_stats)

    def missing(self, journal: CellJournal) -> list:
        done = journal.done_keys()
        return [s for s in self.specs if _key(s) not in done]

    def run(self) -> Path:
        """Run the missing episodes, check hook coverage, write the records; returns the episodes file."""
        try:
            with self.writing():
                return self._run()
        finally:
            self.close_env()

    def _run(self) -> Path:
        journal = CellJournal(self.journal, self.header)
        missing = self.missing(journal)
        bar = tqdm(
            total=len(self.specs),
            initial=len(self.specs) - len(missing),
            desc=self.cfg.ref,
            unit="ep",
            disable=not self.progress,
        )
        bar.set_postfix(successes=sum(e["success"] for e in journal.episodes))

        def finished(records: list[dict]) -> None:
            fired = {name for name, calls in self.report.hook_calls().items() if calls > 0}
            journal.record(records, fired)
            bar.update(len(records))
            bar.set_postfix(successes=sum(e["success"] for e in journal.episodes))

        batches = self._batches(journal)
        first = next(batches, None)
        if first:
            if self._env is None:  # no `start_env`, or it found the journal complete
                self._env = self._start_env(first)
            with self._env.result() as env:
                for batch in itertools.chain([first], batches):
                    run_episodes(self.adapter, env, batch, self.max_steps, finished)
        bar.close()
        return self._finish(journal)

    def _batches(self, journal: CellJournal):
        """The missing episodes in runs of `run_episodes`: all at once, or under the stopping rule batch by batch
        until it decides (each batch chosen after the previous one is journaled)."""
        if self.stopping is None:
            if missing := self.missing(journal):
                yield missing
            return
        while batch := self.stopping.next_batch(journal.episodes, self.missing(journal), self.num_envs):
            yield batch

    def _finish(self, journal: CellJournal) -> Path:
        # Layers the policy never calls (OFT's SigLIP attention-pool head) keep their quantized weights
        # and their scope count, but no activation hook can fire on them: listed as unfired, not refused.
        hooks = hook_summary(self.report.result.hooks, journal.fired)
        missed = [n for n in hooks["unfired"] if not any(fnmatch.fnmatchcase(n, p) for p in self.adapter.idle_layers)]
        if missed:
            raise CellFailed(
                f"cell {self.cfg.ref}: {len(missed)} of {hooks['selected']} selected layers' activation hooks never "
                f"fired, so they ran unquantized: {', '.join(missed)}"
            )
        header = {
            **self.header,
            "hooks": hooks,
            "nonfinite_episodes": sum(bool(e.get("nonfinite_action")) for e in journal.episodes),
            **({} if self.stopping is None else {"stopping": self.stopping.outcome(journal.episodes)}),
        }
        order = {tuple(getattr(s, k) for k in EPISODE_KEY): n for n, s in enumerate(self.specs)}
        episodes = sorted(journal.episodes, key=lambda e: order[tuple(e[k] for k in EPISODE_KEY)])
        expected = len(self.specs) if self.stopping is None else header["stopping"]["rounds_run"] * len(self.cfg.tasks)
        if len(episodes) != expected:
            raise CellFailed(f"cell {self.cfg.ref}: {len(episodes)} episodes recorded, {expected} configured")
        write_cell(self.out_dir, header, episodes)
        if header["nonfinite_episodes"]:
            print(f"cell {self.cfg.ref}: {header['nonfinite_episodes']} of {len(episodes)} episodes ended on a "
                  "non-finite action of the policy (recorded as failures, nonfinite_action: true)", file=sys.stderr)
        return self.out_dir / "episodes.parquet"


def _key(spec) -> tuple:
    return tuple(getattr(spec, k) for k in EPISODE_KEY)


def run_cell(cfg: CellConfig | dict[str, Any], out_dir: str | Path, checkpoint_stamp=None, calibration_stats=None,
             **options) -> Path:
    run = CellRun(cfg, out_dir, checkpoint_stamp, calibration_stats, **options)
    with run.writing():
        run.start_env()
        try:
            run.prepare()
        except BaseException:
            run.close_env()
            raise
        return run.run()
