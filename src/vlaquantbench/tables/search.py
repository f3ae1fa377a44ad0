"""The precision search (`vlaquantbench.search`) over recorded cells: its per-candidate CSV (the Pareto table of
cost against success) and its figure, for `vqb search` and the Snakemake target `tables/search.csv`.

Each candidate's row: its search order, weight-memory ratio to the BF16 model, status (`visited`, `chosen`,
`pruned by CELL`, `not reached`), decision, episodes read, A - B and the success rate at the stop with their
confidence sequences at the candidate's level (alpha / K), and `pareto` (on the cost-success front of the decided
rows). The baseline's row comes first (its success over all its episodes).

Episodes: each candidate's row says how many it read (`episodes_used`), how many its records hold
(`episodes_recorded`: fewer than in full where a live rule stopped it; a DAG runs every candidate of the space, each
under its rule) and how many a run in full needs (`episodes_full`); the summary adds them up against every candidate
of the space run in full.

The chosen allocation by name (`chosen_allocation`, `tables/search_chosen.yaml`): a config that registers the
chosen cell's name under `study.allocations.<name>`, to add after the study's config (`--configfile`), so that a cell
`[seed<N>-]alloc-<name>` is the chosen cell (the same config hash: `vlaquantbench.cells.resolve_allocation`). An
allocation is one cell: one preset on its scope and subset, every other layer at full precision (a cell has one
preset, so the space holds no candidate that mixes formats across components).

A space recorded in part (`space`: every candidate of the space, some without records): the search runs over the
whole space (alpha split over all of it) and gives its answer when the recorded candidates determine it, the
unrecorded ones after the chosen cell `not reached` (0 episodes recorded); otherwise `SearchUndetermined` names the
unrecorded candidates it would read (`vlaquantbench.search.precision_search`). Deciding every candidate
(`decide_all`) needs them all: with some unrecorded it is left out and the summary says so.

Confirmation: the chosen cell and the baseline rerun in full on episodes the search never used, another run seed
(`seed<N>-<cell>`, `held_out`), and contrasted by the paper's fixed-sample task-clustered bootstrap (95%, 5,000
draws, seed 0): `confirmed_not_worse` when its lower end is above -margin (one pre-specified test after the
search, at 2.5% one-sided), `worse` when its upper end is below 0, else `not_confirmed`. Columns `confirm_*` of
the chosen row.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Mapping

import pandas as pd

from vlaquantbench.atomic import atomic_write, write_text
from vlaquantbench.config import validate
from vlaquantbench.errors import UserError
from vlaquantbench.records import contrast_mismatch
from vlaquantbench.records.episodes import Cell
from vlaquantbench.search import (Candidate, SearchDesign, SearchResult, exhaustive, pareto_front, precision_search,
                                  records_decider)
from vlaquantbench.sequential import Design, full_sample_decision
from vlaquantbench.stats import task_clustered_bootstrap

COLOURS = {"chosen": "tab:green", "visited": "tab:blue", "baseline": "black"}
CHOSEN_FILE = "tables/search_chosen.yaml"  # the chosen allocation by name: an output of the target tables/search.csv
DEFAULT_ALLOCATION = "search"


def proxy(header: Mapping) -> float | None:
    """The sum over components of the header's mean relative output error (None where it reports none)."""
    errors = [v["mean_rel_mse"] for v in (header.get("quant_report") or {}).values()
              if isinstance(v, dict) and v.get("mean_rel_mse") is not None]
    return sum(errors) if errors else None


def held_out(ref: str, seed: int) -> str:
    """The cell `ref` on run seed `seed` (`seed<N>-` prefix): the same cell on episodes of other seeds."""
    group, name = ref.rsplit("/", 1)
    if name.startswith("seed"):
        raise UserError(f"cell {ref} already names a run seed: its held-out episodes need a cell without one")
    if seed < 1:
        raise UserError(f"the confirmation's run seed must be 1 or more (0 is the search's own), got {seed}")
    return f"{group}/seed{seed}-{name}"


@dataclass(frozen=True)
class Confirmation:
    cell: str
    baseline: str
    episodes: int
    delta_pp: float
    low_pp: float
    high_pp: float
    decision: str

    def columns(self) -> dict:
        return {"confirm_cell": self.cell, "confirm_episodes": self.episodes, "confirm_delta_pp": self.delta_pp,
                "confirm_bootstrap_low_pp": self.low_pp, "confirm_bootstrap_high_pp": self.high_pp,
                "confirm_decision": self.decision}


def confirm(held: Mapping[str, Cell], chosen: str, baseline: str, seed: int, margin_pp: float) -> Confirmation:
    """The chosen cell against the baseline on run seed `seed`, from `held` (reference -> records); UserError
    naming the cells to run when either is not recorded."""
    cell, against = held_out(chosen, seed), held_out(baseline, seed)
    missing = [ref for ref in (cell, against) if ref not in held]
    if missing:
        raise UserError(f"the confirmation needs the records of {', '.join(missing)} (the chosen cell and its "
                        f"baseline on run seed {seed}): run `vqb rollout {missing[0]}` with the study's config")
    mismatch = contrast_mismatch(held[cell], held[against])
    if mismatch:
        raise UserError(f"confirmation: {cell} cannot be contrasted with {against}: {mismatch}")
    interval = task_clustered_bootstrap(held[cell].episodes, held[against].episodes)
    decision = {"worse": "worse", "not_worse": "confirmed_not_worse", "undecided": "not_confirmed"}[
        full_sample_decision(interval.low, interval.high, Design(margin_pp=margin_pp))]
    return Confirmation(cell, against, len(held[cell].episodes), interval.delta, interval.low, interval.high, decision)


@dataclass
class SearchReport:
    result: SearchResult
    table: pd.DataFrame
    exhaustive_choice: str | None  # the cheapest `not_worse` when every candidate is decided ("" when not run)
    confirmation: Confirmation | None = None
    unrecorded: tuple[str, ...] = ()  # candidates of the space without records (a run cut short)
    decide_all: bool = False

    @property
    def episodes_recorded(self) -> int:
        """The episodes in the candidates' records: what running them cost (a live DAG runs every candidate)."""
        return int(self.table.loc[self.table["order"] > 0, "episodes_recorded"].sum())

    def summary(self) -> list[str]:
        result, chosen = self.result, self.result.chosen
        lines = [f"{result.design.guarantee(len(result.order))}.",
                 f"chosen: {chosen.ref if chosen else 'none (no candidate decided not_worse)'}"
                 + (f" at {chosen.cost_ratio:.3f} x the BF16 weight memory" if chosen else ""),
                 f"episodes: {result.episodes_spent} of {result.episodes_exhaustive} that every candidate run in full "
                 f"would need ({len(result.verdicts)} visited, {len(result.pruned_by)} pruned)",
                 f"recorded: {self.episodes_recorded} episodes in the "
                 + (f"{len(result.order) - len(self.unrecorded)} of {len(result.order)}" if self.unrecorded
                    else f"{len(result.order)}")
                 + f" candidates' records ({self.episodes_recorded / result.episodes_exhaustive:.0%} of every "
                 "candidate in full)"]
        if self.unrecorded:
            lines.append(f"unrecorded: {len(self.unrecorded)} candidate(s) without records, none of which the search "
                         "needs (each pruned, or after the chosen cell: not reached)")
            if self.decide_all:
                lines.append(f"exhaustive: not decided ({len(self.unrecorded)} candidate(s) without records)")
        if self.exhaustive_choice != "":
            same = self.exhaustive_choice == (chosen.ref if chosen else None)
            lines.append(f"exhaustive: {self.exhaustive_choice or 'none'} ({'the same' if same else 'NOT the same'})")
        if self.confirmation is not None:
            c = self.confirmation
            lines.append(f"confirmation on held-out episodes: {c.cell} - {c.baseline}, {c.episodes} episodes each: "
                         f"{c.delta_pp:+.1f} pp [{c.low_pp:+.1f}, {c.high_pp:+.1f}] (task-clustered bootstrap 95%): "
                         f"{c.decision}")
        return lines


def check_levels(cells: Mapping[str, Cell], names: list[str], design: SearchDesign) -> None:
    """Refuse, naming the cell, records that a live rule stopped at the level of a larger space than `names` (alpha
    over more candidates): a folder holding a part of the space, searched as if it were all of it."""
    level = design.per_candidate(len(names)).alpha
    for ref in names:
        stopping = cells[ref].header.get("stopping") if ref in cells else None
        if not stopping or stopping["rounds_run"] >= cells[ref].header["episodes_per_task"]:
            continue
        implied = design.alpha / stopping["alpha"]
        if round(implied) > len(names) and abs(implied - round(implied)) < 1e-6 * implied:
            raise UserError(f"cell {ref}: its records were stopped by a live rule at alpha {stopping['alpha']:.6g} = "
                            f"{design.alpha:g} / {round(implied)}, a space of {round(implied)} candidates, and "
                            f"{len(names)} are searched here (alpha {level:.6g} each): search the whole space, its "
                            "cells without records included (vqb search --space TABLE, or the config's search table)")


def search_records(cells: Mapping[str, Cell], baseline: str, design: SearchDesign, decide_all: bool = False,
                   held: Mapping[str, Cell] | None = None, confirm_seed: int | None = None,
                   space: list[str] | None = None) -> SearchReport:
    """Search over `cells` (reference -> records), every one but `baseline` a candidate; `decide_all`: also
    decide every candidate (the exhaustive choice); `confirm_seed`: confirm the chosen cell on that run seed's
    records in `held`. `space`: the whole space's candidates when some have no records in `cells` (a run cut
    short): the search is over all of them, answered when the recorded ones determine it, else
    `SearchUndetermined` naming the unrecorded ones it needs. UserError naming a cell that cannot be contrasted,
    before any decision."""
    if confirm_seed is not None:
        held_out(baseline, confirm_seed)  # a bad seed is refused before the search
    if baseline not in cells:
        raise UserError(f"the search needs the records of its baseline {baseline}")
    names = [ref for ref in (cells if space is None else dict.fromkeys(space)) if ref != baseline]
    if not names:
        raise UserError(f"the search space of {baseline} holds no candidate cell")
    unrecorded = tuple(ref for ref in names if ref not in cells)
    outside = [ref for ref in cells if ref != baseline and ref not in names]
    if outside:
        raise UserError(f"records of cells outside the search space: {', '.join(outside)}")
    for ref in names:
        mismatch = contrast_mismatch(cells[ref], cells[baseline]) if ref in cells else None
        if mismatch:
            raise UserError(f"cell {ref} cannot be contrasted with {baseline}: {mismatch}")
    check_levels(cells, names, design)
    candidates = [Candidate.from_ref(ref, proxy(cells[ref].header) if ref in cells else None) for ref in names]
    decide = records_decider({r: c.episodes for r, c in cells.items()}, {r: c.header for r, c in cells.items()},
                             baseline)
    result = precision_search(candidates, decide, design, unrecorded)
    rows = [{**row, "episodes_recorded": len(cells[row["cell"]].episodes) if row["cell"] in cells else 0,
             "episodes_full": result.episodes_cap}
            for row in result.rows()]
    rows.insert(0, {"order": 0, "cell": baseline, "cost_ratio": 1.0, "status": "baseline (runs in full)",
                    "episodes_used": len(cells[baseline].episodes),
                    "episodes_recorded": len(cells[baseline].episodes), "episodes_full": len(cells[baseline].episodes),
                    "rate_at_stop": 100.0 * cells[baseline].episodes["success"].mean()})
    front = pareto_front(rows)
    table = pd.DataFrame(rows).assign(pareto=lambda t: t["cell"].isin(front))
    choice = ""
    if decide_all and not unrecorded:
        chosen, _ = exhaustive(candidates, decide, design)
        choice = chosen.ref if chosen else None
    confirmation = None
    if confirm_seed is not None and result.chosen is not None:
        confirmation = confirm(held or {}, result.chosen.ref, baseline, confirm_seed, design.margin_pp)
        for column, value in confirmation.columns().items():
            table.loc[table["cell"] == result.chosen.ref, column] = value
    return SearchReport(result, table, choice, confirmation, unrecorded, decide_all)


def chosen_allocation(report: SearchReport, name: str = DEFAULT_ALLOCATION) -> str:
    """The chosen allocation by name: a config registering the chosen cell's name as `study.allocations.<name>`
    (none chosen: no allocation, so a cell `alloc-<name>` is refused naming what study.allocations defines), what
    the search decided in its comments. UserError naming the name when it is not an allocation name."""
    chosen = report.result.chosen
    group = report.table.loc[report.table["order"] == 0, "cell"].iloc[0].rsplit("/", 1)[0]
    return allocation_config(name, chosen.ref if chosen else None, group, report.summary())


def allocation_config(name: str, chosen: str | None, group: str, summary: list[str]) -> str:
    """`chosen_allocation`'s text from its parts: the allocation `name`, the chosen cell's reference (None: nothing
    chosen), the cells' `<benchmark>/<suite>/<model>` and the search's summary lines (its comments)."""
    import yaml

    allocations = {name: chosen.rsplit("/", 1)[-1]} if chosen else {}
    # The name (and the cell) as study.allocations takes them; with none chosen, the name alone (any cell)
    validate({"allocations": {name: allocations.get(name, "rtn-BASELINE-e2e")}}, "config", f"allocation {name!r}",
             subschema=("study",))
    lines = ["The allocation the precision search chose (tables/search.csv, vlaquantbench.search), by name. Add this",
             "file after the study's config (snakemake --configfile CONFIG tables/search_chosen.yaml, or copy the",
             f"entry into its study.allocations): a cell {group}/[seed<N>-]alloc-{name} is then the chosen cell",
             "under another name (the same config hash, folder and records; vlaquantbench.cells).",
             *summary]
    if chosen is None:
        lines.append(f"No candidate was decided not_worse: no allocation is named, and a cell alloc-{name} is refused.")
    comment = "".join(f"# {line}\n" for line in lines)
    return comment + yaml.safe_dump({"study": {"allocations": allocations}}, sort_keys=False)


def plot_pareto(table: pd.DataFrame, output: str | Path, title: str | None = None) -> Path:
    """Success at the stop (with its confidence sequence) against weight memory, one point per decided row; the
    Pareto front joined, the chosen allocation and the baseline marked."""
    # matplotlib here, not at import: the workflow imports this module while it builds the DAG.
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    decided = table[table["rate_at_stop"].notna()]
    fig, ax = plt.subplots(figsize=(6, 4))
    for row in decided.itertuples():
        kind = "baseline" if row.order == 0 else ("chosen" if row.status == "chosen" else "visited")
        low = getattr(row, "rate_cs_low", float("nan"))
        error = None if pd.isna(low) else [[row.rate_at_stop - low], [row.rate_cs_high - row.rate_at_stop]]
        ax.errorbar(row.cost_ratio, row.rate_at_stop, yerr=error, fmt="o", color=COLOURS[kind], ms=4, capsize=2)
        ax.annotate(row.cell.rsplit("/", 1)[-1], (row.cost_ratio, row.rate_at_stop), fontsize=5,
                    xytext=(3, 3), textcoords="offset points")
    front = decided[decided["pareto"]].sort_values("cost_ratio")
    ax.plot(front["cost_ratio"], front["rate_at_stop"], color="tab:gray", lw=0.8, zorder=0)
    ax.set_xlabel("weight memory / BF16 (committed layer index)")
    ax.set_ylabel("success at the stop (%), confidence sequence at alpha / K")
    ax.legend(handles=[plt.Line2D([], [], marker="o", ls="", color=c) for c in COLOURS.values()],
              labels=list(COLOURS), fontsize=7)
    if title:
        ax.set_title(title, fontsize=7)
    fig.tight_layout()
    with atomic_write(output, "wb") as handle:
        fig.savefig(handle, format="pdf", metadata={"CreationDate": None})
    plt.close(fig)
    return Path(output)


def write_search(cells: Mapping[str, Cell], baseline: str, design: SearchDesign, csv: str | Path,
                 figure: str | Path | None = None, decide_all: bool = False, held: Mapping[str, Cell] | None = None,
                 confirm_seed: int | None = None, chosen: str | Path | None = None,
                 allocation: str = DEFAULT_ALLOCATION, space: list[str] | None = None) -> SearchReport:
    """`search_records` (over `space` when given: the whole space, some of it without records), its CSV, (given
    `figure`) its Pareto figure and (given `chosen`) the chosen allocation named `allocation`
    (`chosen_allocation`). Nothing is written when the search is refused."""
    report = search_records(cells, baseline, design, decide_all, held, confirm_seed, space)
    named = chosen_allocation(report, allocation) if chosen is not None else None  # a bad name: before any write
    write_text(csv, report.table.to_csv(index=False, float_format="%.4f"))
    if figure is not None:
        result = report.result
        plot_pareto(report.table, figure, f"episodes read {result.episodes_spent} of {result.episodes_exhaustive} "
                    f"(every candidate in full); recorded {report.episodes_recorded}")
    if named is not None:
        write_text(chosen, named)
    return report
