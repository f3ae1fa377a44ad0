"""Render a table definition to booktabs LaTeX from cell records."""

from __future__ import annotations

from functools import partial
from pathlib import Path
from typing import Callable, Mapping

import numpy as np

from vlaquantbench.atomic import write_text
from vlaquantbench.records import Cell, read_cell
from vlaquantbench.stats import task_clustered_bootstrap, wilson_interval
from vlaquantbench.tables.definition import BootstrapSpec, ColumnSpec, TableDefinition

MISSING = "--"


def _signed(value: float) -> str:
    # Adding 0.0 turns a rounded -0.0 into +0.0, as the paper prints no-change contrasts.
    return f"{round(value, 1) + 0.0:+.1f}"


def _rate(cell: Cell) -> float:
    return 100.0 * cell.n_successes / cell.n_episodes


def format_value(spec: ColumnSpec, cell: Cell | None, minus: Cell | None, bootstrap: Callable) -> str:
    if cell is None or (spec.minus and minus is None):
        return MISSING
    if spec.stat == "rate":
        return f"{_rate(cell):.1f}"
    if spec.stat == "rate_ci":
        low, high = wilson_interval(cell.n_successes, cell.n_episodes)
        return f"{_rate(cell):.1f} [{low:.0f},{high:.0f}]"
    if spec.stat == "layers":
        return str(cell.quantized_layers)
    if spec.stat == "delta":
        return _signed(_rate(cell) - _rate(minus))
    contrast = bootstrap(cell.episodes, minus.episodes)
    return f"[{_signed(contrast.low)}, {_signed(contrast.high)}]"


def bootstrapper(spec: BootstrapSpec) -> Callable:
    """The table's contrast bootstrap: one generator for all rows (`shared`, consumed in row order) or one per contrast."""
    shared = np.random.default_rng(spec.seed) if spec.stream == "shared" else None
    return partial(task_clustered_bootstrap, draws=spec.draws, seed=spec.seed, rng=shared)


def table_rows(definition: TableDefinition, cells: Mapping[str, Cell]) -> list[list[str]]:
    """Each row as [label, value, ...]: the table's numbers before LaTeX layout (rows in order: a shared
    bootstrap stream is consumed top to bottom)."""
    bootstrap = bootstrapper(definition.bootstrap)
    rows = []
    for row in definition.rows:
        values = [
            format_value(spec, cells.get(row[spec.cell]), cells.get(row[spec.minus]) if spec.minus else None, bootstrap)
            for spec in definition.values
        ]
        rows.append([row["label"], *values])
    return rows


def _line(cells: list[str]) -> str:
    return " & ".join(cells) + r" \\"


# Cells of the demo study run a reduced-width policy with random weights (header `variant: demo`).
DEMO_NOTE = (
    r"\textbf{Demo policy with random weights: these numbers say nothing about the released checkpoint.} "
)


def caption(definition: TableDefinition, cells: Mapping[str, Cell]) -> str:
    demo = any(cells[ref].header.get("variant") == "demo" for ref in definition.refs() if ref in cells)
    return f"\\caption{{{DEMO_NOTE if demo else ''}{definition.caption}}}\\label{{tab:{definition.name}}}"


def render_latex(definition: TableDefinition, cells: Mapping[str, Cell]) -> str:
    header = "\n".join(_line(line) for line in definition.header)
    body = "\n".join(_line(row) for row in table_rows(definition, cells))
    if definition.environment == "longtable":
        return (
            f"\\begin{{longtable}}{{{definition.align}}}\n{caption(definition, cells)}\\\\\n"
            f"\\toprule\n{header}\n\\midrule\\endfirsthead\n"
            f"\\toprule\n{header}\n\\midrule\\endhead\n"
            f"\\bottomrule\\endfoot\n{body}\n\\end{{longtable}}\n"
        )
    return (
        f"\\begin{{table}}[htbp]\n\\centering\n\\begin{{tabular}}{{{definition.align}}}\n\\toprule\n{header}\n\\midrule\n"
        f"{body}\n\\bottomrule\n\\end{{tabular}}\n{caption(definition, cells)}\n\\end{{table}}\n"
    )


def write_table(definition: TableDefinition, cell_paths: Mapping[str, str | Path], output: str | Path) -> Path:
    """Read the table's cells (reference -> record path), render, and write `output`."""
    cells = {ref: read_cell(path) for ref, path in cell_paths.items()}
    return write_text(output, render_latex(definition, cells))
