"""Rollout calibration (paper `app:calib`): unquantized closed-loop episodes with activation
observers on the calibrated components' linear layers; statistics saved under a cache key."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from tqdm import tqdm

from vlaquantbench.cells import CalibrationConfig
from vlaquantbench.config.study import ExecutionConfig
from vlaquantbench.envs import env_settings, make_env, make_suite
from vlaquantbench.models.registry import adapter_class
from vlaquantbench.envs.memory import affordable_workers
from vlaquantbench.runner.cell import calibration_settings, load_policy
from vlaquantbench.runner.checkpoint import CheckpointStamp
from vlaquantbench.runner.loop import run_episodes
from vlaquantbench.runner.provenance import code_revision


def calibrate(
    calib: CalibrationConfig | dict[str, Any],
    output: str | Path,
    checkpoint_stamp: str | Path | None = None,
    *,
    num_envs: int = ExecutionConfig.num_envs,
    torch_threads: int | None = ExecutionConfig.torch_threads,
    progress: bool = ExecutionConfig.progress,
) -> Path:
    """Collect statistics for `calib` (a `cells.CalibrationConfig`, or its canonical form `cells.calibration_config`)
    and save them to `output`."""
    from vlaquantbench.quant import select_layers
    from vlaquantbench.quant.calibration import calibration_key, keyed_fields, save_stats
    from vlaquantbench.quant.steps import flow_clock

    if torch_threads:
        torch.set_num_threads(torch_threads)
    if not isinstance(calib, CalibrationConfig):
        calib = CalibrationConfig.from_dict(calib)
    settings_cfg = calib.calibration
    suite = make_suite(calib.benchmark, calib.suite)
    # Episode i of a task starts from init state (or task variation) i; out-of-range ones fail here, before
    # the policy loads.
    specs = [suite.episode_spec(task, state, settings_cfg.seed)
             for task in settings_cfg.tasks for state in settings_cfg.init_states]
    # Refused, never capped: the statistics are per policy call, so they depend on how many workers share one.
    workers = affordable_workers(min(num_envs, len(specs)), calib.benchmark, calib.suite,
                                 "study.execution.num_envs", cap=False)
    stamp = CheckpointStamp.read(checkpoint_stamp) if checkpoint_stamp is not None else None
    adapter = load_policy(calib, stamp, adapter_class(calib.model))
    settings = calibration_settings(settings_cfg, adapter)
    layers = {}
    for component in settings.components:
        layers.update(select_layers(adapter.model, adapter.components, component).flat())
    fields = dict(
        model=calib.model,
        checkpoint=calib.checkpoint,
        revision=calib.revision,
        init_states=list(settings_cfg.init_states),
        tasks=len(settings_cfg.tasks),
        seed=settings_cfg.seed,
        settings=settings,
        code_revision=code_revision(),
    )
    max_steps = calib.runner.max_steps  # resolved with the cell when the DAG was built
    # exactly the statistics the cell's method declares; per-step ones on the flow steps the adapter clocks
    with settings.observe(layers, flow_clock(adapter.model)) as observer:
        with make_env(calib.benchmark, suite, workers, **env_settings(calib.env, adapter.reads_images)) as env:
            with tqdm(total=len(specs), desc=f"calibrate {calib.model} {calib.suite}", unit="ep",
                      disable=not progress) as bar:
                run_episodes(adapter, env, specs, max_steps, on_finished=lambda records: bar.update(len(records)),
                             overlap=False)  # per-call statistics: reproducible batches
    stats = observer.stats(calibration_key(**fields), keyed_fields(*fields.values()))
    return save_stats(stats, output)
