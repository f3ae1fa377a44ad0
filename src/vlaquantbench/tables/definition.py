"""Table definitions (`config/tables/<name>.yaml`): rows by cell reference, columns by statistic.

```yaml
caption: Action-head subsets under W4A4 ({episodes}) ...   # \\label{tab:<name>} is added
align: lrrr                       # LaTeX column alignment
size: small                       # optional: \\small inside the float; tabcolsep: 4pt likewise
header: [[Quantized subset, "\\#L", "SR \\% [CI]", "$\\Delta$"]]   # one list per header line
cells: {baseline: <benchmark>/<suite>/pi05/rtn-BASELINE-e2e}     # names shared by every row
values:                           # the columns after the row label(s)
  - {stat: layers, cell: cell}
  - {stat: rate_ci, cell: cell, bold_below: 50}   # \\textbf when the rate is below 50 %
  - {stat: delta, cell: cell, minus: baseline}
  - {stat: rates, cells: [seed0, seed1, seed2]}    # "98.0 / 98.5 / 97.5"; null cells are left out
  - {stat: lowest_within, cells: [A4, A6, A8, none], labels: [A4, A6, A8, none], minus: baseline, within_pp: 5, bold: true}
rows:
  - {label: attention, cell: <benchmark>/<suite>/pi05/ablate-W4A4-ah-onlyself_attn}
  - {label: [Model, Suite], cell: ...}           # several label columns
  - {section: '\\emph{OpenVLA-OFT}'}            # a full-width line
  - {midrule: true}
  - {label: SIMPLER-VM, unavailable: 'needs per-episode records that are not published'}
  - {label: BF16, cell: 'latency:openvla_oft/baseline.jsonl'}   # `<source>:<path>`: a file of config `sources`
  - {section: '\\emph{OpenVLA-OFT, baseline {rate}\\%}', cell: ...}  # {rate}: the cell's success rate
  - {label: fc2, cell: ..., override: {params: {bold: true, digits: 0}}}  # column options (bold, digits, key, wrap) for this row, by stat
bootstrap: {draws: 5000, seed: 0, stream: shared}   # optional; for `bootstrap` columns
```
A row names its cells under its own keys (they override `cells`); a null cell prints `--`.
`{episodes}` in the caption is replaced by the episode counts of the table's cells, from the data;
`{steps}` by their step limits (header `max_steps`); `{device}` by the device their episodes ran on (header
`device.name`).
`bootstrap.stream`: `per_contrast` (default) gives every contrast its own `default_rng(seed)`;
`shared` draws all contrasts from one `default_rng(seed)` in row order, as the paper's tab:clustered
does, so there a row's interval depends on the rows above it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from vlaquantbench.config import load_yaml
from vlaquantbench.errors import UserError
from vlaquantbench.stats import BOOTSTRAP_DRAWS, BOOTSTRAP_SEED

STATS = {
    "rate": ("cell",),  # success rate, one decimal
    "rate_ci": ("cell",),  # success rate with integer Wilson bounds (fixed-sample: `--` bounds for a stopped cell)
    "layers": ("cell",),  # quantized layers from the header's quant_report
    "nonfinite": ("cell",),  # episodes ended by a non-finite (NaN) action of the policy
    "delta": ("cell", "minus"),  # A - B in pp; for a cell run under the stopping rule, paired over the rounds it read
    "bootstrap": ("cell", "minus"),  # task-clustered bootstrap interval of A - B (fixed-sample: `--` for a cell the
    # stopping rule stopped before its cap; a cell under the rule is compared with B's episodes of its rounds)
    "delta_cs": ("cell", "minus"),  # for a cell run under the stopping rule: the anytime-valid confidence sequence
    # of A - B, paired over the rounds the rule read, at its level (`--` for a fixed-design cell)
    "rate_cs": ("cell",),  # likewise the confidence sequence of the cell's success rate
    "mean_subtasks": ("cell",),  # CALVIN: mean completed subtasks per chain, two decimals
    "mean_progress": ("cell",),  # VLABench: mean progress score in percent, one decimal
    "episodes": ("cell",),  # the cell's episode count, from its data
    "rates": ("cells",),  # several cells' rates joined by " / " (e.g. seeds 0/1/2)
    "lowest_within": ("cells", "labels", "minus", "within_pp"),  # label of the first cell within N pp of `minus`
    "median_ms": ("cell", "field"),  # median over episodes of a per-episode latency in s, printed in ms
    "max": ("cell", "field"),  # maximum over episodes (a session's peak memory: each episode logs the peak so far)
    "value": ("cell", "key"),  # a number from a .json measurement file: dotted `key` ({name} filled from the row's `fill`),
    # `index` into a list, times `scale`, `signed` for a leading +
    "params": ("cell",),  # weight parameters of the layers the cell quantizes (its scope and subset on the model's
    # layer index, built from the architecture on the meta device), as 28.7K / 117.4M / 7.44B; `--` for none
    "stopped": ("cell",),  # the sequential rule's stop (header `stopping`): "worse@30" = decision and episodes
    # its test used; `--` for a fixed-design cell
    "mean_ci": ("cell", "field"),  # mean over episodes of a per-episode number (jerk, action_rate) with its
    # task-clustered bootstrap interval, as "0.012 [0.010,0.015]" (`digits`, default 3)
    "header": ("cell", "key"),  # a number at dotted `key` of the cell's run header (quant_report.ah.mean_rel_mse),
    # in scientific notation with `digits` (default 1); `--` where the header records null or the cell is a summary row
    "text": ("cell", "key"),  # a string: dotted `key` of a .json measurement file, or a field of the cell's run
    # header or summary row (`checkpoint`); `wrap: path|texttt`
}
DEFAULT_DIGITS = {"median_ms": 1, "max": 2, "value": 2, "params": 1, "mean_ci": 3, "header": 1}
ROW_KINDS = ("label", "section", "midrule")


@dataclass(frozen=True)
class BootstrapSpec:
    draws: int = BOOTSTRAP_DRAWS
    seed: int = BOOTSTRAP_SEED
    stream: str = "per_contrast"


@dataclass(frozen=True)
class ColumnSpec:
    stat: str
    cell: str
    minus: str | None = None
    bold_below: float | None = None  # \\textbf{} when the cell's success rate is below this (%)
    bold: bool = False  # always \\textbf{}
    cells: tuple[str, ...] = ()  # row keys of the cells a multi-cell stat reads, in order
    labels: tuple[str, ...] = ()  # what lowest_within prints for each of `cells`
    within_pp: float | None = None
    field: str = ""  # median_ms / max: the episode column
    key: str = ""  # value: the JSON key
    index: int | None = None  # value: position in a JSON list
    scale: float = 1.0  # value: printed multiplied by this
    digits: int | None = None  # decimals printed (median_ms 1, max 2, value 2 unless given)
    signed: bool = False  # value: print a leading + for positive numbers
    wrap: str = ""  # text: printed inside \\path{} or \\texttt{}

    def keys(self) -> list[str]:
        """The row keys naming this column's cells."""
        return [key for key in (self.cell, self.minus, *self.cells) if key]


@dataclass(frozen=True)
class TableDefinition:
    name: str
    align: str
    header: list[list[str]]
    values: list[ColumnSpec]
    rows: list[dict[str, Any]]
    caption: str
    environment: str = "tabular"
    bootstrap: BootstrapSpec = BootstrapSpec()
    size: str = ""
    tabcolsep: str = ""

    @classmethod
    def from_dict(cls, name: str, raw: dict[str, Any], where: str | None = None) -> "TableDefinition":
        """A table from its YAML content, already valid under schema `table` (`load_table`: fields,
        types, allowed keys and values); here the checks across fields. UserError names `where`."""
        where = where or f"table {name!r}"
        values = []
        for index, spec in enumerate(raw["values"]):
            stat = spec["stat"]
            if stat not in STATS:
                raise UserError(f"{where}: values.{index}.stat: {stat!r} is not allowed; allowed values: {', '.join(STATS)}")
            missing = [key for key in STATS[stat] if not spec.get(key)]
            if missing:
                raise UserError(f"{where}: values.{index} ({stat}) needs {', '.join(missing)}")
            if len(spec.get("labels") or ()) not in (0, len(spec.get("cells") or ())):
                raise UserError(f"{where}: values.{index} needs one label per cell")
            values.append(
                ColumnSpec(stat=stat, cell=spec.get("cell", ""), minus=spec.get("minus"), bold_below=spec.get("bold_below"),
                           bold=bool(spec.get("bold")), cells=tuple(spec.get("cells") or ()),
                           labels=tuple(str(label) for label in spec.get("labels") or ()), within_pp=spec.get("within_pp"),
                           field=spec.get("field", ""), key=spec.get("key", ""), index=spec.get("index"),
                           scale=float(spec.get("scale", 1.0)), digits=spec.get("digits", DEFAULT_DIGITS.get(stat)),
                           signed=bool(spec.get("signed")), wrap=spec.get("wrap", ""))
            )
        shared = raw.get("cells") or {}
        rows = []
        for index, row in enumerate(raw["rows"]):
            kinds = [kind for kind in ROW_KINDS if kind in row]
            if len(kinds) != 1:
                raise UserError(f"{where}: rows.{index} needs exactly one of {', '.join(ROW_KINDS)}, got {sorted(row)}")
            if "{rate}" in row.get("section", "") and not row.get("cell"):
                raise UserError(f"{where}: rows.{index}: the section prints {{rate}} but names no cell")
            if kinds[0] != "label" or "unavailable" in row:
                rows.append(dict(row))
                continue
            unknown = sorted(set(row.get("override", {})) - {spec.stat for spec in values})
            if unknown:
                raise UserError(f"{where}: rows.{index} ({row['label']}) overrides no column of stat {', '.join(unknown)}")
            merged = {**shared, **row}
            for spec in values:
                for key in spec.keys():
                    if key not in merged:
                        raise UserError(f"{where}: rows.{index} ({row['label']}) names no cell {key!r}")
            rows.append(merged)
        bootstrap = BootstrapSpec(**raw.get("bootstrap", {}))
        layout = {key: str(raw.get(key, "")) for key in ("size", "tabcolsep")}
        return cls(name, raw["align"], raw["header"], values, rows, raw["caption"], raw.get("environment", "tabular"),
                   bootstrap, **layout)

    def cell_rows(self) -> list[dict[str, Any]]:
        """The rows that print numbers of cells (not sections, rules or unavailable rows)."""
        return [row for row in self.rows if "label" in row and "unavailable" not in row]

    def contrasts(self) -> list[tuple[str, str]]:
        """The (cell, minus) pairs its difference columns (`delta`, `bootstrap`) print, in row order, each once."""
        pairs = [(row[spec.cell], row[spec.minus]) for row in self.cell_rows() for spec in self.values
                 if spec.minus and not spec.cells and row[spec.cell] and row[spec.minus]]
        return list(dict.fromkeys(pairs))

    def refs(self) -> list[str]:
        """Every cell reference the table reads, sorted: the workflow's inputs for this table."""
        keys = {key for spec in self.values for key in spec.keys()}
        sections = {row["cell"] for row in self.rows if "section" in row and row.get("cell")}
        return sorted({row[key] for row in self.cell_rows() for key in keys if row[key]} | sections)


def load_table(path: str | Path) -> TableDefinition:
    """Read `config/tables/<name>.yaml` (schema `table`); the table's name is the file's stem."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"unknown table {path.stem!r}: no {path}")
    return TableDefinition.from_dict(path.stem, load_yaml(path, "table"), where=str(path))
