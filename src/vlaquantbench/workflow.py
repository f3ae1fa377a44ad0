"""What the Snakemake rules ask of a validated config, in one place.

A cell is named by a reference `<benchmark>/<suite>/<model>/<cell>` in the authors' naming
(the cell name's grammar: `vlaquantbench.cells`). With `records_dir` set, its
records are read from there (the authors' `<ref>.jsonl` or this project's `<ref>/` folder);
without it, the DAG produces the cell under `results/cells/<config-hash>/`. A named allocation
(`.../alloc-<name>`, `study.allocations`) reads the records of the cell it stands for either way.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property, lru_cache
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

from vlaquantbench.errors import UserError

if TYPE_CHECKING:
    from vlaquantbench.config.study import StudyConfig
    from vlaquantbench.figures import ScopeRecoveryFigure
    from vlaquantbench.tables import TableDefinition


@dataclass(frozen=True)
class WorkflowConfig:
    raw: dict[str, Any]
    basedir: Path

    @classmethod
    def from_snakemake(cls, config: dict[str, Any], basedir: str | Path) -> "WorkflowConfig":
        return cls(raw=config, basedir=Path(basedir))

    @property
    def records_dir(self) -> Path | None:
        value = self.raw.get("records_dir")
        return Path(value) if value else None

    @property
    def manifest(self) -> Path | None:
        value = self.raw.get("manifest")
        return Path(value) if value else None

    # --- records and tables (analysis rules) ---

    @property
    def records_root(self) -> Path:
        """Where the record files the tables read live: `records_dir`, or the DAG's cell folders."""
        return self.records_dir or Path(CELLS_DIR)

    @cached_property
    def study(self) -> "StudyConfig":
        """The typed `study` section (the Snakefile has validated the whole config already)."""
        from vlaquantbench.config.study import StudyConfig

        return StudyConfig.from_dict(self.raw.get("study"))

    def study_cells(self) -> dict[str, dict[str, Any]]:
        """Canonical configs of every cell the listed tables read, keyed by config hash (what the rollout
        rules run). A bad cell (unknown suite, model, preset, method or subset, or a subset pattern that
        matches no layer) is refused here, while the DAG is built, naming the table file and the cell."""
        from vlaquantbench import cells  # the DAG's cell hashing; imported only when cells are produced

        configs = {}
        for name in self._listed_tables():
            for ref in self.table_record_refs(name):
                try:
                    cfg = cells.cell_config(ref, self.study)
                except UserError as err:
                    raise UserError(f"{self.tables_dir / f'{name}.yaml'}: {err}") from None
                configs[cells.config_hash(cfg)] = cfg
                if cfg.get("sequential"):  # the cell it stops against runs too, whether a table reads it or not
                    against = cfg["sequential"]["against"]
                    configs[against["config_hash"]] = cells.cell_config(against["ref"], self.study)
        return configs

    def cell_input(self, ref: str) -> str:
        """The record file of cell `ref`: the authors' `.jsonl` or a cell folder's `episodes.parquet`."""
        if self.records_dir is None:
            from vlaquantbench import cells  # the DAG's cell hashing; imported only when cells are produced

            config_hash = cells.config_hash(cells.cell_config(ref, self.study))
            return f"{CELLS_DIR}/{config_hash}/episodes.parquet"
        found = self._recorded_cells().get(self.recorded_ref(ref))
        if found is None:
            raise UserError(
                f"cell {ref} is not in records_dir {self.records_dir}: "
                f"neither {ref}.jsonl nor {ref}/episodes.parquet exists"
            )
        return str(found)

    def cell_header(self, ref: str) -> str | None:
        """The header.json that `read_cell` reads beside a cell folder's episodes.parquet (None for the
        authors' .jsonl, which holds its header)."""
        from vlaquantbench.records.cell import EPISODES_FILE, HEADER_FILE

        record = Path(self.cell_input(ref))
        return str(record.with_name(HEADER_FILE)) if record.name == EPISODES_FILE else None

    @property
    def tables_dir(self) -> Path:
        """Table definitions: the config's `tables_dir`; else `config/tables/`, or the study's own
        (`study.tables_dir`) when the DAG runs the cells itself (the demo study renders a few rows with a
        demo caption)."""
        if self.raw.get("tables_dir"):  # the config's own tables, whichever way its records come
            return self.basedir / self.raw["tables_dir"]
        study_dir = (self.raw.get("study") or {}).get("tables_dir")
        if self.records_dir is None and study_dir:
            return self.basedir / study_dir
        return self.basedir / "config" / "tables"

    @cached_property
    def _definitions(self) -> dict[Path, Any]:
        return {}

    def _definition(self, path: Path, load: Callable[[Path], Any]) -> Any:
        """A table or figure definition, read and validated once per workflow parse: the rules' input
        functions ask for each many times while the DAG is built."""
        if path not in self._definitions:
            self._definitions[path] = load(path)
        return self._definitions[path]

    def table_file(self, name: str) -> str:
        return str(self.tables_dir / f"{name}.yaml")

    def table(self, name: str) -> "TableDefinition":
        from vlaquantbench.tables import load_table

        return self._definition(Path(self.table_file(name)), load_table)

    def table_names(self) -> list[str]:
        """Tables defined by a `<tables_dir>/<name>.yaml` (the paper tables built from records)."""
        return sorted(path.stem for path in self.tables_dir.glob("*.yaml"))

    def figure_file(self, name: str) -> str:
        return str(self.basedir / "config" / "figures" / f"{name}.yaml")

    def figure(self, name: str) -> "ScopeRecoveryFigure":
        from vlaquantbench.figures import load_figure

        return self._definition(Path(self.figure_file(name)), load_figure)

    def layer_index_table_file(self, name: str) -> str:
        """The definition of a table counted on the models' layer index, without records (tab:vla_params)."""
        return str(self.basedir / "config" / "layer_index_tables" / f"{name}.yaml")

    @property
    def success_summary(self) -> Path | None:
        """The authors' per-cell summary: the source of cells whose episodes are not in `records_dir`."""
        value = self.raw.get("success_summary")
        return Path(value) if value else None

    def recorded_ref(self, ref: str) -> str:
        """The reference under which `records_dir` holds the records of cell `ref`: `ref`, or for a named allocation
        (`[seed<N>-][steps<N>-]alloc-<name>`) not recorded under its own name, the cell it stands for
        (`study.allocations`; an unknown name is refused naming it)."""
        group, _, name = ref.rpartition("/")
        if self.records_dir is None or "alloc-" not in name or ref in self._recorded_cells():
            return ref
        from vlaquantbench.cells import resolve_allocation  # the cell grammar, only for a cell named so

        return f"{group}/{resolve_allocation(name, self.study.allocations, ref)}"

    def record_refs(self, refs: list[str], target: str) -> list[str]:
        """Of `target`'s cells `refs`, those read from episode records. With `records_dir` set, a cell without
        records comes from `success_summary`; a cell in neither is an error naming it (at DAG build, before any job)."""
        refs = [ref for ref in refs if not is_source_ref(ref)]
        if self.records_dir is None:
            return refs
        recorded = self._recorded_cells()
        absent = [ref for ref in refs if self.recorded_ref(ref) not in recorded]
        if absent:
            from vlaquantbench.records.summary import read_summary

            summarized = read_summary(self.success_summary) if self.success_summary else {}
            for ref in absent:
                if ref not in summarized:
                    where = f"nor in success_summary {self.success_summary}" if self.success_summary else "and no success_summary is set"
                    raise UserError(f"{target}: cell {ref} is neither in records_dir {self.records_dir} {where}")
        return [ref for ref in refs if self.recorded_ref(ref) in recorded]

    def recorded(self, refs: list[str]) -> list[str]:
        """Of the cells `refs`, those with episode records: every one when the DAG produces them (no
        `records_dir`), else those `records_dir` holds (a named allocation by the cell it stands for)."""
        if self.records_dir is None:
            return list(refs)
        recorded = self._recorded_cells()
        return [ref for ref in refs if self.recorded_ref(ref) in recorded]

    def summary_input(self, refs: list[str], target: str) -> list[str]:
        """`[success_summary]` when some of `target`'s cells `refs` come from it, else `[]` (a rule input)."""
        cells = [ref for ref in refs if not is_source_ref(ref)]
        if self.records_dir is None or len(self.record_refs(refs, target)) == len(cells):
            return []
        return [str(self.success_summary)]

    def source_files(self, refs: list[str], target: str) -> dict[str, str]:
        """The measurement files `target` reads (`<source>:<path>` cells -> file), from config `sources`."""
        found = {}
        for ref in filter(is_source_ref, refs):
            source, path = ref.split(":", 1)
            folder = (self.raw.get("sources") or {}).get(source)
            if folder is None:
                raise UserError(f"{target}: cell {ref} names source {source!r}, which config `sources` does not define")
            file = Path(folder) / path
            # A DAG that produces its measurement files (the replay rules) leaves a missing one to
            # Snakemake, which names the file and the rule lacking it; published files must exist now.
            if self.records_dir is not None and not file.is_file():
                raise UserError(f"{target}: cell {ref}: {file} does not exist")
            found[ref] = str(file)
        return found

    def search_space(self) -> tuple[str, list[str]]:
        """The precision search's baseline and whole space (the config's `search`): the cells of `search.table` of
        the baseline's benchmark, suite and model, the baseline among them. UserError without a `search` section or
        without exactly one baseline cell in the table."""
        search = self.raw.get("search")
        if not search:
            raise UserError("tables/search.csv needs a `search` section in the config (its table, baseline, alpha, "
                            "margin_pp)")
        refs = list(dict.fromkeys(self.table(search["table"]).refs()))
        baseline = search.get("baseline", "rtn-BASELINE-e2e")
        named = [ref for ref in refs if baseline in (ref, ref.rsplit("/", 1)[-1])]
        if len(named) != 1:
            raise UserError(f"search.baseline {baseline!r}: {len(named)} such cells in table {search['table']} "
                            f"({', '.join(named) or 'none'}); the search needs exactly one")
        group = named[0].rsplit("/", 1)[0]
        return named[0], [ref for ref in refs if ref.rsplit("/", 1)[0] == group]

    def table_record_refs(self, name: str) -> list[str]:
        return self.record_refs(self.table(name).refs(), f"tables/{name}.tex")

    def table_summary(self, name: str) -> list[str]:
        return self.summary_input(self.table(name).refs(), f"tables/{name}.tex")

    def table_sources(self, name: str) -> dict[str, str]:
        return self.source_files(self.table(name).refs(), f"tables/{name}.tex")

    def data_source(self) -> str:
        """Where a table's numbers come from, in words (report captions)."""
        records = f"episode records in {self.records_dir}" if self.records_dir else f"cells run by this DAG ({CELLS_DIR})"
        summary = f"; cells without records from the summary {self.success_summary}" if self.records_dir and self.success_summary else ""
        return records + summary

    def record_checks(self) -> str:
        """What a rendering job checks its records against, in words (report captions): the frozen manifest
        and its SHA-256, or, without one, the records' schema and headers only."""
        if self.manifest is None:
            return f"their headers and the episode schema (no frozen manifest; {BUILT_MANIFEST} lists them)"
        from vlaquantbench.manifest import sha256_file

        digest = f"SHA-256 {sha256_file(self.manifest)}" if self.manifest.is_file() else "missing"
        return f"manifest {self.manifest} ({digest}), their headers and the episode schema"

    def cell_refs(self) -> list[str]:
        """Cells the summary lists and the manifest check covers: every recorded cell in `records_dir`
        (a superset of what any table reads from records), or, when the DAG runs the cells, every cell
        a table listed in `tables` reads."""
        if self.records_dir is not None:
            return sorted(self._recorded_cells())
        return sorted({ref for name in self._listed_tables() for ref in self.table_record_refs(name)})

    def checked_refs(self, refs: list[str], target: str) -> list[str]:
        """`refs` of `target`, provided the manifest check covers them all (so no table reads an unchecked record)."""
        covered = set(self.cell_refs())
        unchecked = [ref for ref in refs if ref not in covered and self.recorded_ref(ref) not in covered]
        if unchecked:
            raise UserError(
                f"{target} reads cell {unchecked[0]}, which the manifest check does not cover: "
                "add a table that lists it to `tables` in the config"
            )
        return refs

    def _listed_tables(self) -> list[str]:
        """The tables in the config's `tables` that have a definition in `tables_dir`."""
        defined = set(self.table_names())
        return [name for name in self.raw.get("tables", []) if name in defined]

    def _recorded_cells(self) -> dict[str, Path]:
        return _cells_in(self.records_dir)


def is_source_ref(ref: str) -> bool:
    """`<source>:<path>` names a measurement file (latency, fidelity), not a cell's episode records."""
    return ":" in ref


CELLS_DIR = "results/cells"
BUILT_MANIFEST = "results/records/manifest.tsv"


@lru_cache(maxsize=None)
def _cells_in(records_dir: Path) -> dict[str, Path]:
    """The cells under `records_dir`, scanned once per workflow run (input functions ask repeatedly)."""
    from vlaquantbench.records import find_cells

    return find_cells(records_dir)
