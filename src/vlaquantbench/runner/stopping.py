"""The stopping rule live (issue 32): a cell under `study.sequential` stops once its answer is known.

The cell runs its episodes in whole task-interleaved rounds (round k is episode k of every task), in
batches of the fewest rounds that fill its simulator workers. After each batch the anytime-valid test of
`vlaquantbench.sequential` reads the cell's complete rounds paired with the same rounds of the
`against` cell's records (same tasks, init states and seeds) and the cell stops when it decides
(`worse`, or `not_worse` by the margin) or at its cap, `episodes_per_task` rounds (`undecided`).

The decision is the test's first crossing, a function of the outcomes in round order alone: a batch of
several rounds may run past it (those episodes are recorded too, `rounds_run` >= `rounds_used`), and a
resumed cell decides exactly as an uninterrupted one. A journal that already holds the decision runs
only the missing episodes of the rounds it has begun, so the records are whole rounds; the header's
`stopping` says the decision, the episodes used and run, and both tests' log capital at the stop.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import pandas as pd

from vlaquantbench.cells import CellConfig
from vlaquantbench.errors import UserError
from vlaquantbench.records.cell import check_declared_episodes, read_cell
from vlaquantbench.sequential import Design, SequentialResult, paired_rounds, stopping_rule


class StoppingRule:
    """The test of one sequential cell (its `CellConfig`) against the records at `against_records`."""

    def __init__(self, cfg: CellConfig, against_records: str | Path | None):
        design = cfg.sequential
        self.ref, self.against = cfg.ref, design.against
        if against_records is None:
            raise UserError(f"cell {self.ref}: study.sequential tests it against {self.against.ref}, whose records "
                            "were not given (run that cell first)")
        baseline = check_declared_episodes(read_cell(against_records))
        if baseline.header.get("config_hash") != self.against.config_hash:
            raise UserError(f"{baseline.path}: config hash {baseline.header.get('config_hash')!r}, but cell {self.ref} "
                            f"is tested against {self.against.ref} with config hash {self.against.config_hash!r}")
        if baseline.header.get("stopping"):
            raise UserError(f"{baseline.path}: cell {self.against.ref} stopped early itself; a sequential cell is "
                            "tested against a cell that ran all its episodes")
        self.design = Design(alpha=design.alpha, margin_pp=design.margin_pp)
        self.tasks, self.cap = list(cfg.tasks), int(cfg.episodes_per_task)
        self.baseline = baseline.episodes[baseline.episodes["task_id"].isin(self.tasks)]
        if sorted(self.baseline["task_id"].unique()) != sorted(self.tasks):
            raise UserError(f"{baseline.path}: records tasks {sorted(baseline.episodes['task_id'].unique())}, but cell "
                            f"{self.ref} runs tasks {self.tasks}")
        if int(self.baseline.groupby("task_id").size().min()) < self.cap:
            raise UserError(f"{baseline.path}: fewer than {self.cap} episodes on some task, the cap of cell {self.ref}")

    @staticmethod
    def _rounds(episodes: list[dict[str, Any]], tasks: list[int]) -> tuple[int, int]:
        """(complete rounds: leading rounds with every task's episode, rounds begun: highest episode + 1)."""
        done = {(e["task_id"], e["episode"]) for e in episodes}
        complete = 0
        while all((task, complete) in done for task in tasks):
            complete += 1
        return complete, max((e["episode"] + 1 for e in episodes), default=0)

    def result(self, episodes: list[dict[str, Any]]) -> SequentialResult | None:
        """The test on the complete rounds of `episodes` (the journal's): its decision at the first crossing, or
        `undecided` at the cap; None while it has neither."""
        complete, _ = self._rounds(episodes, self.tasks)
        if complete == 0:
            return None
        cell = pd.DataFrame([e for e in episodes if e["episode"] < complete])[["task_id", "episode", "success"]]
        baseline = self.baseline[self.baseline["episode"] < complete]
        result = stopping_rule(paired_rounds(cell, baseline, (self.ref, self.against.ref)), self.design)
        return result if result.decision != "undecided" or complete >= self.cap else None

    def next_batch(self, episodes: list[dict[str, Any]], missing: list, workers: int) -> list:
        """The missing episode specs to run next ([] when the cell is done): the rounds begun, once decided;
        otherwise up to the fewest further whole rounds that give every worker an episode, within the cap."""
        complete, begun = self._rounds(episodes, self.tasks)
        if self.result(episodes) is not None:
            target = begun
        else:
            target = min(self.cap, max(begun, complete + math.ceil(workers / len(self.tasks))))
        return [spec for spec in missing if spec.episode < target]

    def outcome(self, episodes: list[dict[str, Any]]) -> dict[str, Any]:
        """The header's `stopping` record of a finished cell, whose `episodes` are whole rounds."""
        result = self.result(episodes)
        complete, begun = self._rounds(episodes, self.tasks)
        if result is None or complete != begun:
            raise UserError(f"cell {self.ref}: the stopping rule has not finished ({complete} complete rounds of "
                            f"{begun} begun, cap {self.cap})")
        return {
            "decision": result.decision,
            "rounds_used": result.rounds_used,
            "episodes_used": result.episodes_used,
            "rounds_run": complete,
            "log_capital_worse": result.log_capital_worse,
            "log_capital_not_worse": result.log_capital_not_worse,
            "alpha": self.design.alpha,
            "margin_pp": self.design.margin_pp,
            "against": self.against.ref,
        }
