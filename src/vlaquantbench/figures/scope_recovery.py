"""fig:scope_recovery: (a) isolated action-head groups vs their union, (b) success along nested scopes."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

from vlaquantbench.atomic import atomic_write
from vlaquantbench.config import load_yaml
from vlaquantbench.errors import UserError
from vlaquantbench.records import Cell
from vlaquantbench.stats import wilson_interval
from vlaquantbench.tables.latex import read_cells


@dataclass(frozen=True)
class ScopeRecoveryFigure:
    baseline: str
    isolated: list[dict[str, Any]]  # {label, cell}
    nested: list[dict[str, Any]]  # {label, cell, repeats?: [refs]}

    def refs(self) -> list[str]:
        entries = self.isolated + self.nested
        repeats = [ref for entry in self.nested for ref in entry.get("repeats", [])]
        return sorted({self.baseline, *(entry["cell"] for entry in entries), *repeats})


def load_figure(path: str | Path) -> ScopeRecoveryFigure:
    path = Path(path)
    if not path.is_file():
        raise UserError(f"unknown figure {path.stem!r}: no {path}")
    return ScopeRecoveryFigure(**load_yaml(path, "figure"))


def _rate(cell: Cell) -> float:
    return 100.0 * cell.n_successes / cell.n_episodes


def plot_scope_recovery(
    figure: ScopeRecoveryFigure, cell_paths: Mapping[str, str | Path], output: str | Path, summary: str | Path | None = None
) -> Path:
    """Draw the figure from its cells' records (`cell_paths`), seed repeats included; cells without records (the
    reference data's seed-1/2 repeats of these scopes) come from `summary`."""
    # matplotlib here, not at import: the workflow loads the figure's definition while it builds the DAG.
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cells = read_cells(figure.refs(), cell_paths, summary, "figure scope_recovery")
    baseline = _rate(cells[figure.baseline])
    fig, (left, right) = plt.subplots(1, 2, figsize=(7.5, 2.8), constrained_layout=True)

    isolated = [cells[entry["cell"]] for entry in figure.isolated]
    rates = [_rate(cell) for cell in isolated]
    low, high = wilson_interval([c.n_successes for c in isolated], [c.n_episodes for c in isolated])
    positions = range(len(isolated))
    left.errorbar(positions, rates, yerr=[rates - low, high - rates], fmt="o", capsize=3, color="C0")
    left.set_xticks(list(positions), [entry["label"] for entry in figure.isolated])
    left.set_title("(a) isolated groups vs. union", fontsize=9)

    nested = [cells[entry["cell"]] for entry in figure.nested]
    layers = [cell.quantized_layers for cell in nested]
    right.plot(layers, [_rate(cell) for cell in nested], "o-", color="C1")
    for entry, count in zip(figure.nested, layers):
        repeats = [_rate(cells[ref]) for ref in entry.get("repeats", [])]
        right.plot([count] * len(repeats), repeats, "o", mfc="none", color="C1")
        right.annotate(entry["label"], (count, _rate(cells[entry["cell"]])), fontsize=7, xytext=(3, 3),
                       textcoords="offset points")  # fmt: skip
    right.set_xlabel("quantized action-head layers")
    right.set_title("(b) nested scopes", fontsize=9)

    if any(cell.header.get("variant") == "demo" for cell in cells.values()):  # summary rows carry no variant
        fig.suptitle("Demo policy with random weights: says nothing about the released checkpoint", fontsize=8)
    for axis in (left, right):
        axis.axhline(baseline, ls="--", color="gray", lw=1)
        axis.set_ylim(-5, 105)
        axis.set_ylabel("success rate (%)")
    with atomic_write(output, "wb") as handle:
        fig.savefig(handle, format="pdf", metadata={"CreationDate": None})
    plt.close(fig)
    return output
