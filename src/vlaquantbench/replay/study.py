"""A replay study definition (which configurations, formats and roles) plus the per-format
`analysis.json` files it produced or the authors published."""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path


from vlaquantbench.config import load_yaml
from vlaquantbench.errors import UserError
from vlaquantbench.quant.subsets import get_subset
from vlaquantbench.records.summary import read_summary

STUDIES = Path(__file__).with_name("studies")


def load_definition(name_or_path: str | Path, folder: Path, kind: str, schema: str) -> dict:
    """A YAML definition by name (`<folder>/<name>.yaml`) or by path, validated against `schema`."""
    path = Path(name_or_path)
    if not path.suffix:
        path = folder / f"{name_or_path}.yaml"
    if not path.exists():
        raise UserError(f"unknown {kind} {str(name_or_path)!r}: no {path}")
    return load_yaml(path, schema)


def load_study(name_or_path: str | Path = "pi05_libero_spatial") -> dict:
    """A replay study; a configuration with a subset takes its scope and layer count from config/scopes.yaml."""
    study = load_definition(name_or_path, STUDIES, "replay study", "replay_study")
    for name, conf in study["configurations"].items():
        if conf["subset"] is not None:
            try:
                subset = get_subset(study["model"], conf["subset"])
            except UserError as err:
                raise UserError(f"replay study {str(name_or_path)!r}: configurations.{name}.subset: {err}") from None
            conf.update(scope=subset.scope, layers=subset.layers)
    return study


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


@dataclass(frozen=True)
class StudyResults:
    study: dict
    analyses: dict[str, dict]  # format -> analysis.json content

    @classmethod
    def from_dir(cls, analysis_dir: str | Path, study: dict) -> "StudyResults":
        """Read `<analysis_dir>/<format>/analysis.json` for every format of the study."""
        return cls.from_files({f: Path(analysis_dir) / f / "analysis.json" for f in study["formats"]}, study)

    @classmethod
    def read(cls, analyses: str | Path | Mapping[str, str | Path], study: dict) -> "StudyResults":
        """From a mapping format -> analysis.json (what a rule's input declares) or a folder of them."""
        if isinstance(analyses, Mapping):
            return cls.from_files(dict(analyses), study)
        return cls.from_dir(analyses, study)

    @classmethod
    def from_files(cls, paths: dict[str, str | Path], study: dict) -> "StudyResults":
        paths = {fmt: Path(p) for fmt, p in paths.items()}
        absent = [str(p) for p in paths.values() if not p.exists()]
        if absent:
            raise UserError(f"replay analysis files missing (replay_analysis_dir): {', '.join(absent)}")
        analyses = {}
        for fmt, path in paths.items():
            analyses[fmt] = json.loads(path.read_text())
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
