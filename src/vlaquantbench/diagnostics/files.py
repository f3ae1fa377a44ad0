"""Per-layer activation diagnostics files (the authors' `diagnostics/v2/<model>-<scope>-<preset>.json`
layout, which this project's collection writes too).

    {model, suite, scope, preset, spec,
     provenance: {checkpoint, checkpoint_revision, seed, tasks, episodes_from, episodes,
                  vqb_commit, mujoco, torch, python, gpu, created},
     layers: {name: {act_kurtosis, out_rel_err, act_rel_err, act_dispersion,
                     calls, in_features, out_features, params}}}
"""

from __future__ import annotations

import fnmatch
import json
from dataclasses import dataclass
from pathlib import Path

from vlaquantbench.errors import UserError
from vlaquantbench.textfiles import read_parsed

DIAGNOSTICS = ("act_kurtosis", "out_rel_err", "act_rel_err", "act_dispersion")
HEADER_FIELDS = ("model", "suite", "scope", "preset", "provenance", "layers")
PROVENANCE_FIELDS = ("checkpoint", "checkpoint_revision", "seed", "tasks", "episodes_from", "episodes", "mujoco", "torch")


@dataclass(frozen=True)
class Diagnostics:
    header: dict
    layers: dict[str, dict]
    path: Path

    @classmethod
    def read(cls, path: str | Path) -> "Diagnostics":
        path = Path(path)
        if not path.exists():
            raise UserError(f"diagnostics file {path} does not exist")
        data = read_parsed(path, json.loads, "JSON")
        missing = [k for k in HEADER_FIELDS if k not in data]
        missing += [f"provenance.{k}" for k in PROVENANCE_FIELDS if k not in data.get("provenance", {})]
        if missing:
            raise UserError(f"diagnostics file {path} lacks fields {missing}")
        for name, entry in data["layers"].items():
            absent = [k for k in DIAGNOSTICS if k not in entry]
            if absent:
                raise UserError(f"diagnostics file {path}: layer {name!r} lacks {absent}")
        header = {k: v for k, v in data.items() if k != "layers"}
        return cls(header, data["layers"], path)

    def select(self, only: list[str] | None, exclude: list[str] | None) -> list[str]:
        """Layer names kept by include (`only`) and `exclude` glob patterns, as a quantizer applies them."""
        return [
            n
            for n in self.layers
            if (not only or any(fnmatch.fnmatchcase(n, p) for p in only))
            and not (exclude and any(fnmatch.fnmatchcase(n, p) for p in exclude))
        ]

    def scope_average(self, names: list[str]) -> dict[str, float]:
        """Each diagnostic averaged with equal weight per layer (not per parameter or token)."""
        return {d: sum(self.layers[n][d] for n in names) / len(names) for d in DIAGNOSTICS}
