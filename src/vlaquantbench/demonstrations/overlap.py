"""The demonstrations' task variations never start an evaluated or calibration episode.

Closed-loop episode e of a task of the demonstrations' benchmark starts from task variation e (its suite's
`episode_spec`), and calibration episodes from the variations `study.calibration` names; the demonstrations
record variations `first_variation .. first_variation + max_attempts_per_task - 1`. A policy evaluated on a
scene it was trained on measures memory, not control, so rule demonstrations refuses, while the DAG is built,
a config whose ranges meet: every range its study names on that benchmark (each model's evaluation episodes,
the calibration protocol), whether or not its cells are in the DAG (a study reading its records from
`records_dir` trains and evaluates on them all the same), and the calibration variations of the benchmark's
cells that are (`calib_set<k>` shifts them by 2k).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from vlaquantbench.errors import UserError

if TYPE_CHECKING:
    from vlaquantbench.config.study import StudyConfig
    from vlaquantbench.demonstrations.dataset import DemonstrationConfig


@dataclass(frozen=True)
class VariationRange:
    """Task variations `first..last` and the config fields that set them, in words."""

    first: int
    last: int
    source: str

    def __str__(self) -> str:
        return f"variations {self.first}..{self.last} ({self.source})"

    def meets(self, other: VariationRange) -> bool:
        return self.first <= other.last and other.first <= self.last


def demonstrated_range(config: DemonstrationConfig) -> VariationRange:
    return VariationRange(config.first_variation, config.last_variation,
                          f"demonstrations.first_variation {config.first_variation}, "
                          f"max_attempts_per_task {config.max_attempts_per_task}")


def study_ranges(study: StudyConfig, benchmark: str, cells: Iterable[dict[str, Any]] = ()) -> list[VariationRange]:
    """The variations `study` evaluates on `benchmark` (each model's episodes per task) and calibrates on (its
    protocol), and those the `cells` of `benchmark` (canonical configs, `cells.CellConfig.to_dict`) calibrate on."""
    from vlaquantbench.cells import episodes_per_task  # the model registry: only when a config is checked

    ranges = []
    for model in study.models:
        episodes, field = episodes_per_task(study, model, benchmark)
        ranges.append(VariationRange(0, episodes - 1, f"{field} {episodes}: evaluation episode e starts from variation e"))
    calibration = study.calibration
    ranges.append(VariationRange(calibration.first_init_state, calibration.first_init_state + calibration.episodes - 1,
                                 f"study.calibration.first_init_state {calibration.first_init_state}, "
                                 f"episodes {calibration.episodes}"))
    for cell in cells:
        init_states = (cell.get("calibration") or {}).get("init_states")
        if cell["benchmark"] == benchmark and init_states:
            ranges.append(VariationRange(min(init_states), max(init_states), f"cell {cell['ref']}'s calibration episodes"))
    return ranges


def check_disjoint(demonstrated: VariationRange, used: Iterable[VariationRange], setting: str) -> None:
    """UserError `<demonstrated> meet <range>` for the first of `used` that meets the demonstrations' range,
    saying to move `setting` (what sets the range that was checked)."""
    for other in used:
        if demonstrated.meets(other):
            raise UserError(f"the demonstrations' {demonstrated} meet the {other} at "
                            f"{max(demonstrated.first, other.first)}..{min(demonstrated.last, other.last)}: a "
                            f"policy would be evaluated on scenes it was trained on; move {setting} so that they "
                            "do not meet")


def check_disjoint_from_evaluation(config: DemonstrationConfig, study: StudyConfig,
                                   cells: Iterable[dict[str, Any]] = ()) -> None:
    """UserError naming the first range of `study_ranges` on the demonstrations' benchmark that their variations
    meet."""
    check_disjoint(demonstrated_range(config), study_ranges(study, config.benchmark, cells),
                   "demonstrations.first_variation")
