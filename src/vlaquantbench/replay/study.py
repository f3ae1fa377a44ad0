"""A replay study definition (which configurations, formats and roles; a YAML file of the project's config,
`config/replay/<name>.yaml`, on any benchmark) plus the per-format `analysis.json` files it produced or the authors
published."""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path


from vlaquantbench.config import load_yaml
from vlaquantbench.config.study import RunnerConfig
from vlaquantbench.envs import BENCHMARK_SUITES, benchmark_settings, check_ids
from vlaquantbench.errors import UserError
from vlaquantbench.quant.subsets import get_subset
from vlaquantbench.records.summary import read_summary
from vlaquantbench.textfiles import read_parsed


def load_definition(path: str | Path, kind: str, schema: str) -> dict:
    """The YAML definition at `path`, validated against `schema`; UserError naming the `kind` when it is missing."""
    if not Path(path).is_file():
        raise UserError(f"unknown {kind} {str(path)!r}: no such file")
    return load_yaml(path, schema)


def load_study(path: str | Path) -> dict:
    """The replay study at `path` (its YAML); a configuration with a subset takes its scope and layer count from
    config/scopes.yaml. UserError naming `runner.<setting>` when the study sets an env setting its benchmark does
    not declare, or a value its declaration does not admit (`envs.benchmark_settings`)."""
    study = load_definition(path, "replay study", "replay_study")
    study.setdefault("runner", {})
    benchmark_settings(study["benchmark"], study["runner"],
                       {key: f"replay study {str(path)!r}: runner.{key}" for key in study["runner"]})
    for name, conf in study["configurations"].items():
        if conf["subset"] is not None:
            try:
                subset = get_subset(study["model"], conf["subset"])
            except UserError as err:
                raise UserError(f"replay study {str(path)!r}: configurations.{name}.subset: {err}") from None
            conf.update(scope=subset.scope, layers=subset.layers)
    return study


def study_name(path: str | Path) -> str:
    """What names a replay study's folders (`results/replay/<name>/`): its YAML file's stem."""
    return Path(path).stem


def with_formats(study: dict, formats: list[str] | None) -> dict:
    """The study restricted to `formats` (e.g. a demo run replaying W4A4 only)."""
    if not formats:
        return study
    unknown = [f for f in formats if f not in study["formats"]]
    if unknown:
        raise UserError(f"replay.formats {unknown} are not formats of the study ({', '.join(study['formats'])})")
    keep = [f for f in study["formats"] if f in formats]
    order = [f for f in study["all_formats_order"] if f in formats]
    return {**study, "formats": keep, "all_formats_order": order,
            "bias_format": study["bias_format"] if study["bias_format"] in formats else keep[-1]}


def analysis_files(analysis_dir: str | Path, formats: list[str]) -> dict[str, Path]:
    """format -> `<analysis_dir>/<format>/analysis.json`: where the replay DAG writes (and the authors
    published) each format's analysis."""
    return {fmt: Path(analysis_dir) / fmt / "analysis.json" for fmt in formats}


@dataclass(frozen=True)
class RecordSettings:
    """A replay study's full-precision recording: which policy, which (task, init state) trajectories."""

    model: str
    variant: str
    suite: str
    benchmark: str
    tasks: list[int]
    init_states: list[int]
    observe: list[str]  # layers whose inputs the probe summarizes (e.g. the expert down_proj)
    # The env settings the study's cells set (its `runner`): with the model's client's conventions and the
    # benchmark's defaults, what the recording's env renders and steps as those cells' env does.
    runner: dict = field(default_factory=dict)
    checkpoint: str | None = None
    revision: str | None = None
    checkpoint_dir: str | None = None
    max_steps: int | None = None  # default: the model's step limit on the suite (`models.client.step_limit`)
    executed_chunk: int | None = RunnerConfig.executed_chunk  # None: the model's released client
    flow_steps: int = RunnerConfig.flow_steps
    run_seed: int = 0
    device: str = RunnerConfig.device
    threads: int = 1  # CPU kernels' blocking depends on it; the replay uses the same count

    @classmethod
    def from_study(cls, study: dict, options: dict | None = None) -> "RecordSettings":
        """The study's recording, with the workflow's `replay` options (validated by the config schema: variant, tasks,
        init_states, max_steps, checkpoint, revision, checkpoint_dir, device, threads, executed_chunk, flow_steps,
        run_seed) taking precedence; its `study` and `formats` choose the study and its replays, not the recording's settings."""
        options = {k: v for k, v in (options or {}).items() if k not in ("formats", "study")}
        base = {"variant": "full", "tasks": study["tasks"], "init_states": study["init_states"]}
        if options.get("variant", "full") == "full":  # a demo policy has random weights, no checkpoint
            base.update(checkpoint=study["checkpoint"], revision=study["revision"])
        settings = cls(model=study["model"], suite=study["suite"], benchmark=study["benchmark"], observe=study["observe"],
                       runner=study["runner"], **{**base, **options})
        # Checked here, while the DAG is built: a recording job would fail on them only after loading the policy.
        size = BENCHMARK_SUITES[study["benchmark"]][settings.suite]
        for key, ids, count, what in (("tasks", settings.tasks, size.tasks, "tasks"),
                                      ("init_states", settings.init_states, size.init_states, "official init states per task")):
            field = f"replay.{key}" if key in options else f"the replay study's {key}"
            check_ids(field, ids, count, f"{settings.suite} has {count} {what}")
        return settings

    def trajectory_files(self) -> list[str]:
        """File names of the recorded trajectories (`t<task>_e<init state>.npz`), in recording order."""
        return [f"t{task}_e{init_state}.npz" for task in self.tasks for init_state in self.init_states]


@dataclass(frozen=True)
class StudyResults:
    study: dict
    analyses: dict[str, dict]  # format -> analysis.json content

    @classmethod
    def from_files(cls, paths: Mapping[str, str | Path], study: dict) -> "StudyResults":
        """Read the analysis file of every format of the study (`paths`: format -> analysis.json)."""
        paths = {fmt: Path(p) for fmt, p in paths.items()}
        if sorted(paths) != sorted(study["formats"]):
            raise UserError(f"replay analyses given for formats {sorted(paths)}, the study has {study['formats']}")
        absent = [str(p) for p in paths.values() if not p.exists()]
        if absent:
            raise UserError(f"replay analysis files missing (replay_analysis_dir): {', '.join(absent)}")
        analyses = {}
        for fmt, path in paths.items():
            analyses[fmt] = read_parsed(path, json.loads, "JSON")
            missing = [c for c in study["configurations"] if c not in analyses[fmt]["configs"]]
            if missing:
                raise UserError(f"{path} has no configurations {missing}")
        return cls(study, analyses)

    def config(self, fmt: str, name: str) -> dict:
        return self.analyses[fmt]["configs"][name]

    def cell(self, fmt: str, name: str) -> str:
        """Cell reference `<benchmark>/<suite>/<model>/<cell>` of the closed-loop counterpart."""
        s = self.study
        return f"{s['benchmark']}/{s['suite']}/{s['model']}/" + s["configurations"][name]["cell"].format(preset=fmt)


def success_rates(summary_csv: str | Path | None) -> dict[str, float]:
    """Success rate (%) per cell reference from a summary table with the authors' summary.csv
    columns (this project's `tables/summary.csv` or the authors' own)."""
    if not summary_csv:
        return {}
    return {ref: 100.0 * cell.n_successes / cell.n_episodes for ref, cell in read_summary(summary_csv).items()}
