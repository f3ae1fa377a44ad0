"""Render a table definition from its cells (episode records or summary rows) through the one writer."""

from __future__ import annotations

import json
import logging
from collections import Counter
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

from vlaquantbench.errors import UserError
from vlaquantbench.records import Cell, read_checked_cell
from vlaquantbench.records.summary import SummaryCell, read_summary
from vlaquantbench.sequential import contrast_at_stop, ran_in_full, rate_at_stop
from vlaquantbench.stats import task_clustered_bootstrap, task_clustered_mean, wilson_interval
from vlaquantbench.tables.booktabs import MIDRULE, Booktabs
from vlaquantbench.tables.definition import BootstrapSpec, ColumnSpec, TableDefinition

MISSING = "--"
UNAVAILABLE = "n/a"


@dataclass(frozen=True)
class MeasurementFile:
    """A `.json` of measured values (e.g. the authors' action-fidelity summaries): numbers, no episodes."""

    ref: str
    values: dict
    path: Path
    episodes = None

    @classmethod
    def read(cls, ref: str, path: str | Path) -> "MeasurementFile":
        path = Path(path)
        try:
            return cls(ref, json.loads(path.read_text()), path)
        except (OSError, json.JSONDecodeError) as err:
            raise UserError(f"cell {ref}: {path} is not a readable JSON file ({err})") from err

    def get(self, key: str, index: int | None = None):
        """The number at dotted `key` (e.g. `configs.attention.executed_action_mae`), element `index` of a list."""
        return float(self.lookup(key, index))

    def lookup(self, key: str, index: int | None = None):
        """What the file holds at dotted `key`, element `index` of a list."""
        value = self.values
        for part in key.split("."):
            if not isinstance(value, dict) or part not in value:
                raise UserError(f"cell {self.ref}: {self.path} has no {key!r}")
            value = value[part]
        if index is not None:
            if not isinstance(value, list) or not -len(value) <= index < len(value):
                raise UserError(f"cell {self.ref}: {self.path}: {key!r} has no element {index}")
            value = value[index]
        return value


AnyCell = Cell | SummaryCell | MeasurementFile


def _signed(value: float) -> str:
    # Adding 0.0 turns a rounded -0.0 into +0.0, as the paper prints no-change contrasts.
    return f"{round(value, 1) + 0.0:+.1f}"


# Parameter counts as the paper prints them: 28.7K, 117.4M, 7.44B.
SI_PREFIXES = ((1e9, "B"), (1e6, "M"), (1e3, "K"))


def _si(count: int, digits: int) -> str:
    scale, prefix = next(((scale, prefix) for scale, prefix in SI_PREFIXES if count >= scale), (1, ""))
    return f"{count / scale:.{digits}f}{prefix}"


def _counted(ref: str, cell: AnyCell | None = None) -> dict[str, int]:
    # cells (the cell-name grammar and its registries) only where a table counts layers: every other table job
    # skips importing it.
    from vlaquantbench.cells import quantized_counts

    group, name = ref.rsplit("/", 1)
    config = cell.header.get("config") if isinstance(cell, Cell) else None
    if config and "alloc-" in name:  # a named allocation (study.allocations): the cell its recorded config names
        name = "-".join(config[key] for key in ("method", "preset", "scope", "subset") if config[key])
    return quantized_counts(f"{group}/{name}")


def _text(cell: AnyCell, key: str, ref: str) -> str:
    """A string of the cell: at `key` of a .json measurement file, else a field of its run header or summary row."""
    if isinstance(cell, MeasurementFile):
        return str(cell.lookup(key))
    if not cell.header.get(key):
        raise UserError(f"cell {ref}: {cell.path} records no {key}")
    return str(cell.header[key])


def _header_number(cell: AnyCell, key: str, ref: str, digits: int) -> str:
    """The number at dotted `key` of a cell's run header, e.g. `quant_report.ah.mean_rel_mse`: `--` where it is
    null or its record is absent below the header's own field (a component outside the cell's scope, a method
    without calibration rows); UserError for a header without the field at all (a misspelt key, or records
    older than the field)."""
    if not isinstance(cell, Cell):
        return MISSING
    first, *rest = key.split(".")
    if first not in cell.header:
        raise UserError(f"cell {ref}: its header {cell.path} has no {first} (stat header, key {key})")
    value: Any = cell.header[first]
    for part in rest:
        value = value.get(part) if isinstance(value, dict) else None
    return MISSING if value is None else f"{float(value):.{digits}e}"


def _rate(cell: AnyCell) -> float:
    return 100.0 * cell.n_successes / cell.n_episodes


def _mean(cell: AnyCell, column: str, field: str, ref: str) -> float:
    if isinstance(cell, SummaryCell):
        if column not in cell.means:
            raise UserError(f"cell {ref}: the summary {cell.path} has no {column}")
        return cell.means[column]
    values = cell.episodes[field].dropna() if field in cell.episodes else ()
    if not len(values):
        raise UserError(f"cell {ref}: its episodes record no {field} ({cell.path})")
    return float(values.mean())


def _sequential(cell: AnyCell) -> dict | None:
    """The stopping rule's record of a cell that ran under it, else None."""
    return cell.header.get("stopping") if isinstance(cell, Cell) else None


def _stopped_early(cell: AnyCell) -> bool:
    """A cell the stopping rule stopped before its cap: its episode count was chosen by its data."""
    return isinstance(cell, Cell) and not ran_in_full(cell.header)


def _same_rounds(minus: AnyCell, minus_ref: str, cell: AnyCell):
    """B's episodes of the rounds a sequential cell A recorded (all of B's for a fixed-design A)."""
    episodes = _episodes(minus, minus_ref, "a contrast")
    stopping = _sequential(cell)
    return episodes if not stopping else episodes[episodes["episode"] < stopping["rounds_run"]]


def _episodes(cell: AnyCell, ref: str, stat: str):
    if cell.episodes is None:
        raise UserError(f"cell {ref}: {stat} needs per-episode records; only its summary row is available")
    return cell.episodes


def _multi_cell(spec: ColumnSpec, row: dict, cells: Mapping[str, AnyCell]) -> str:
    listed = [cells.get(row[key]) if row[key] else None for key in spec.cells]
    if spec.stat == "rates":
        return " / ".join(f"{_rate(cell):.1f}" for cell in listed if cell is not None) or MISSING
    reference = cells.get(row[spec.minus]) if row[spec.minus] else None
    if reference is None:
        return MISSING
    # Candidates in the listed order (ascending width): the first within `within_pp` of the reference.
    for label, cell in zip(spec.labels, listed):
        if cell is not None and _rate(cell) >= _rate(reference) - spec.within_pp:
            return label
    return MISSING


def format_value(spec: ColumnSpec, row: dict, cells: Mapping[str, AnyCell], bootstrap: Callable) -> str:
    text = _format(spec, row, cells, bootstrap)
    return rf"\textbf{{{text}}}" if spec.bold else text


def _format(spec: ColumnSpec, row: dict, cells: Mapping[str, AnyCell], bootstrap: Callable) -> str:
    if spec.cells:
        return _multi_cell(spec, row, cells)
    ref, minus_ref = row[spec.cell], row[spec.minus] if spec.minus else None
    cell, minus = cells.get(ref) if ref else None, cells.get(minus_ref) if minus_ref else None
    if cell is None or (spec.minus and minus is None):
        return MISSING
    if spec.stat == "value":
        value = cell.get(spec.key.format(**row.get("fill", {})), spec.index) * spec.scale
        return f"{round(value, spec.digits) + 0.0:{'+' if spec.signed else ''}.{spec.digits}f}"
    if spec.stat in ("median_ms", "max", "mean_ci"):
        values = _episodes(cell, ref, spec.stat)
        if spec.field not in values or values[spec.field].isna().all():
            raise UserError(f"cell {ref}: its episodes record no {spec.field} ({cell.path})")
        if spec.stat == "mean_ci":
            interval = task_clustered_mean(values, spec.field)
            return f"{interval.mean:.{spec.digits}f} [{interval.low:.{spec.digits}f},{interval.high:.{spec.digits}f}]"
        column = values[spec.field].dropna()
        return f"{1000.0 * column.median():.{spec.digits}f}" if spec.stat == "median_ms" else f"{column.max():.{spec.digits}f}"
    if spec.stat == "episodes":
        text = str(cell.n_episodes)
    elif spec.stat == "rate":
        text = f"{_rate(cell):.1f}"
    elif spec.stat == "rate_ci":
        low, high = wilson_interval(cell.n_successes, cell.n_episodes)
        text = f"{_rate(cell):.1f} [{MISSING}]" if _stopped_early(cell) else f"{_rate(cell):.1f} [{low:.0f},{high:.0f}]"
    elif spec.stat == "layers":  # a summary row has no run header: counted on the model's layer index
        text = str(_counted(ref)["layers"] if isinstance(cell, SummaryCell) else cell.quantized_layers)
    elif spec.stat == "params":
        params = _counted(ref, cell)["params"]
        text = _si(params, spec.digits) if params else MISSING
    elif spec.stat == "header":
        text = _header_number(cell, spec.key, ref, spec.digits)
    elif spec.stat == "text":
        text = _text(cell, spec.key, ref)
        text = rf"\{spec.wrap}{{{text}}}" if spec.wrap else text
    elif spec.stat == "stopped":
        stopping = cell.header.get("stopping") if isinstance(cell, Cell) else None
        text = MISSING if not stopping else f"{_escape(stopping['decision'])}@{stopping['episodes_used']}"
    elif spec.stat == "nonfinite":
        text = MISSING if cell.n_nonfinite is None else str(cell.n_nonfinite)
    elif spec.stat == "rate_cs" and _sequential(cell):
        rate = rate_at_stop(_episodes(cell, ref, spec.stat), cell.header)
        text = f"[{rate.low:.1f}, {rate.high:.1f}]"
    elif spec.stat in ("delta", "delta_cs") and _sequential(cell):
        contrast = contrast_at_stop(_episodes(cell, ref, spec.stat), cell.header, _episodes(minus, minus_ref, spec.stat))
        text = _signed(contrast.estimate) if spec.stat == "delta" else f"[{_signed(contrast.low)}, {_signed(contrast.high)}]"
    elif spec.stat in ("delta_cs", "rate_cs"):  # a fixed-design cell: its fixed-sample intervals are the other stats
        text = MISSING
    elif spec.stat == "delta":
        text = _signed(_rate(cell) - _rate(minus))
    elif spec.stat == "mean_subtasks":
        text = f"{_mean(cell, 'mean_subtasks', 'subtasks_completed', ref):.2f}"
    elif spec.stat == "mean_progress":
        text = f"{100.0 * _mean(cell, 'mean_progress', 'progress_score', ref):.1f}"
    elif _stopped_early(cell):  # bootstrap: a fixed-sample interval, not over a sample its data chose
        text = MISSING
    else:
        contrast = bootstrap(_episodes(cell, ref, "bootstrap"), _same_rounds(minus, minus_ref, cell))
        text = f"[{_signed(contrast.low)}, {_signed(contrast.high)}]"
    if spec.bold_below is not None and _rate(cell) < spec.bold_below:
        text = rf"\textbf{{{text}}}"
    return text


def bootstrapper(spec: BootstrapSpec) -> Callable:
    """The table's contrast bootstrap: one generator for all rows (`shared`, consumed in row order) or one per contrast."""
    shared = np.random.default_rng(spec.seed) if spec.stream == "shared" else None
    return partial(task_clustered_bootstrap, draws=spec.draws, seed=spec.seed, rng=shared)


def _section(row: dict, cells: Mapping[str, AnyCell]) -> str:
    """A full-width line; `{rate}` in it is the success rate of the row's `cell` (e.g. a block's baseline)."""
    text = row["section"]
    return text.replace("{rate}", f"{_rate(cells[row['cell']]):.1f}") if "{rate}" in text else text


def _labels(row: dict) -> list[str]:
    label = row["label"]
    return list(label) if isinstance(label, list) else [label]


def table_rows(definition: TableDefinition, cells: Mapping[str, AnyCell]) -> list[list[str] | None]:
    """Each line as [label(s), value, ...] or MIDRULE: the table's numbers before layout (rows in order:
    a shared bootstrap stream is consumed top to bottom)."""
    bootstrap = bootstrapper(definition.bootstrap)
    width = len(definition.header[-1]) if definition.header else 1
    rows: list[list[str] | None] = []
    for row in definition.rows:
        if "midrule" in row:
            rows.append(MIDRULE)
        elif "section" in row:
            rows.append([rf"\multicolumn{{{width}}}{{l}}{{{_section(row, cells)}}}"])
        elif "unavailable" in row:
            rows.append([*_labels(row), *[UNAVAILABLE] * len(definition.values)])
        else:
            specs = [replace(spec, **row.get("override", {}).get(spec.stat, {})) for spec in definition.values]
            read = _task_episodes(row, cells) if "task" in row else cells
            rows.append([*_labels(row), *(format_value(spec, row, read, bootstrap) for spec in specs)])
    return rows


def _task_episodes(row: dict, cells: Mapping[str, AnyCell]) -> dict[str, AnyCell]:
    """The row's cells restricted to their episodes of the row's `task` (a task name): a per-task row."""
    restricted = {}
    for ref in {row[key] for key in row if isinstance(row[key], str) and row[key] in cells}:
        cell = cells[ref]
        episodes = _episodes(cell, ref, f"task row {row['task']!r}")
        if "task_name" not in episodes:
            raise UserError(f"cell {ref}: its episodes record no task_name, so row {row['label']!r} cannot select "
                            f"task {row['task']!r} ({cell.path})")
        selected = episodes[episodes["task_name"] == row["task"]]
        if selected.empty:
            raise UserError(f"cell {ref}: no episode of task {row['task']!r} (row {row['label']!r}); its tasks: "
                            f"{', '.join(sorted(episodes['task_name'].unique()))} ({cell.path})")
        restricted[ref] = replace(cell, episodes=selected.reset_index(drop=True))
    return restricted


# Cells of the demo study run a reduced-width policy with random weights (header `variant: demo`).
DEMO_NOTE = (
    r"\textbf{Demo policy with random weights: these numbers say nothing about the released checkpoint.} "
)


def _escape(text: str) -> str:
    return text.replace("_", r"\_")


def _short_names(refs: list[str]) -> list[str]:
    """`<model>/<cell>` of each reference, or `<suite>/<model>/<cell>` where that alone would repeat a name."""
    short = [ref.split("/", 2)[-1] for ref in refs]
    return short if len(set(short)) == len(set(refs)) else [ref.split("/", 1)[-1] for ref in refs]


def _per_cell(values: dict[str, int], unit: str) -> str:
    """`<common> <unit>, <n> for <cells>, ...`: the most common value and the exceptions."""
    common, _ = Counter(values.values()).most_common(1)[0]
    exceptions = []
    for n in sorted({n for n in values.values() if n != common}):
        names = sorted(ref.split("/", 2)[-1] for ref, value in values.items() if value == n)
        if len(names) > 3:  # many cells: name their models
            names = sorted({name.split("/")[0] + " cells" for name in names})
        exceptions.append(f"{n} for {', '.join(_escape(name) for name in names)}")
    return ", ".join([f"{common} {unit}", *exceptions])


def episode_counts(refs: list[str], cells: Mapping[str, AnyCell]) -> str:
    """The cells' episode counts as a caption phrase, from the data: the common count and the exceptions."""
    counts = {ref: cells[ref].n_episodes for ref in refs if ref in cells and not isinstance(cells[ref], MeasurementFile)}
    return _per_cell(counts, "episodes per cell") if counts else "no episodes"


def step_limits(refs: list[str], cells: Mapping[str, AnyCell]) -> str:
    """The cells' step limits (header `max_steps`) as a caption phrase, from the data."""
    limits = {ref: cells[ref].header["max_steps"] for ref in refs
              if isinstance(cells.get(ref), Cell) and cells[ref].header.get("max_steps")}
    return "at most " + _per_cell(limits, "steps per episode") if limits else "step limits not recorded"


def devices(refs: list[str], cells: Mapping[str, AnyCell]) -> str:
    """The device the cells' episodes ran on (header `device.name`), as a caption phrase, from the data: "one
    NVIDIA H100 80GB HBM3", or the most common device and each other with its cells where they differ."""
    names = {ref: (cells[ref].header.get("device") or {}).get("name") for ref in refs if isinstance(cells.get(ref), Cell)}
    if not any(names.values()):
        return "no recorded device"
    names = {ref: _escape(name or "no recorded device") for ref, name in names.items()}
    if len(set(names.values())) == 1:
        return "one " + next(iter(names.values()))
    return _per_cell(names, "for the other cells")


def semantics_note(refs: list[str], cells: Mapping[str, AnyCell]) -> str:
    """A caption sentence, and a warning in the log, when the table's recorded cells were quantized under
    different quantization-semantics versions (header `quant_semantics`; none: records from before it)."""
    versions = {cells[ref].header.get("quant_semantics") for ref in refs if isinstance(cells.get(ref), Cell)}
    if len(versions) < 2:
        return ""
    named = ", ".join(sorted("unversioned" if v is None else f"version {v}" for v in versions))
    logging.getLogger(__name__).warning("table mixes cells of quantization-semantics %s", named)
    return f" Note: these cells were quantized under different quantization-semantics versions ({named})."


def caption(definition: TableDefinition, cells: Mapping[str, AnyCell]) -> str:
    refs = definition.refs()
    demo = any(getattr(cells.get(ref), "header", {}).get("variant") == "demo" for ref in refs)
    text = (definition.caption.replace("{episodes}", episode_counts(refs, cells)).replace("{steps}", step_limits(refs, cells))
            .replace("{device}", devices(refs, cells)))
    summary = sorted({cells[ref].path.name for ref in refs if isinstance(cells.get(ref), SummaryCell)})
    if summary:
        from_summary = [ref for ref in refs if isinstance(cells.get(ref), SummaryCell)]
        which = "All cells" if len(from_summary) == len([r for r in refs if r in cells]) else (
            f"{len(from_summary)} of {len([r for r in refs if r in cells])} cells ("
            + ", ".join(_escape(name) for name in _short_names(from_summary)) + ")"
        )
        text += f" {which} come from the authors' per-cell summary ({_escape(', '.join(summary))}), not from episode records."
    unavailable = [row for row in definition.rows if "unavailable" in row]
    for row in unavailable:
        text += f" {_labels(row)[0]}: {UNAVAILABLE}, {row['unavailable']}."
    return f"{DEMO_NOTE if demo else ''}{text}{semantics_note(refs, cells)}"


def booktabs(definition: TableDefinition, cells: Mapping[str, AnyCell], notes: list[str] | None = None) -> Booktabs:
    return Booktabs(
        align=definition.align,
        header=definition.header,
        rows=table_rows(definition, cells),
        caption=caption(definition, cells),
        label=f"tab:{definition.name}",
        environment=definition.environment,
        size=definition.size,
        tabcolsep=definition.tabcolsep,
        notes=notes or [],
    )


def render_latex(definition: TableDefinition, cells: Mapping[str, AnyCell]) -> str:
    return booktabs(definition, cells).latex()


def read_cells(
    refs: list[str], cell_paths: Mapping[str, str | Path], summary: str | Path | None = None, owner: str = "table"
) -> dict[str, AnyCell]:
    """The cells `refs` of `owner`: records where `cell_paths` has them, else the summary's row; a cell in
    neither is an error naming it."""
    cells: dict[str, AnyCell] = {
        ref: MeasurementFile.read(ref, path) if str(path).endswith(".json") else read_checked_cell(ref, path)
        for ref, path in cell_paths.items()
    }
    rows = read_summary(summary) if summary else {}
    for ref in refs:
        if ref not in cells:
            if ref not in rows:
                where = f" nor in the summary {summary}" if summary else " and no summary is configured (success_summary)"
                raise UserError(f"{owner}: cell {ref} is neither in the records{where}")
            cells[ref] = rows[ref]
    return cells


def write_table(
    definition: TableDefinition,
    cell_paths: Mapping[str, str | Path],
    output: str | Path,
    summary: str | Path | None = None,
    html_output: str | Path | None = None,
    notes: list[str] | None = None,
) -> Path:
    """Read the table's cells (reference -> record path, the rest from `summary`), render, and write `output`
    (and its browser page `html_output`)."""
    cells = read_cells(definition.refs(), cell_paths, summary, f"table {definition.name}")
    return booktabs(definition, cells, notes).write(output, html_output)
