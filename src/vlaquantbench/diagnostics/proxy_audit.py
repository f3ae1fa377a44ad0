"""Proxy audit (paper `tab:proxy_audit`): do scope-averaged layer diagnostics rank closed-loop
success loss? Spearman correlations with average ranks for ties, one per model and diagnostic."""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping
from pathlib import Path

import pandas as pd

from vlaquantbench.atomic import atomic_write
from vlaquantbench.diagnostics.files import DIAGNOSTICS, Diagnostics
from vlaquantbench.errors import UserError
from vlaquantbench.quant.subsets import get_subset
from vlaquantbench.replay.study import load_definition, success_rates
from vlaquantbench.tables.booktabs import Booktabs

COLUMNS = {"act_kurtosis": "Kurtosis", "out_rel_err": "Output error", "act_rel_err": "Activation error",
           "act_dispersion": "Dispersion"}


def load_cohort(path: str | Path) -> dict:
    """The cohort definition at `path` (a YAML file of the project's config, e.g. `config/cohorts/proxy_audit.yaml`);
    its subsets must be named subsets of config/scopes.yaml for their model."""
    cohort = load_definition(path, "diagnostic cohort", "cohort")
    for model, spec in cohort["models"].items():
        for subset in spec["subsets"]:
            try:
                get_subset(model, subset)
            except UserError as err:
                raise UserError(f"diagnostic cohort {str(path)!r}: models.{model}.subsets: {err}") from None
    return cohort


def diagnostics_files(cohort: dict, diagnostics_dir: str | Path) -> dict[str, Path]:
    """model -> its diagnostics file `<diagnostics_dir>/<cohort's diagnostics name>.json`."""
    return {model: Path(diagnostics_dir) / f"{spec['diagnostics']}.json" for model, spec in cohort["models"].items()}


def _checked(cohort: dict, diagnostics: Mapping[str, str | Path]) -> dict[str, Path]:
    if sorted(diagnostics) != sorted(cohort["models"]):
        raise UserError(f"diagnostics given for models {sorted(diagnostics)}; the cohort has {sorted(cohort['models'])}")
    return {model: Path(path) for model, path in diagnostics.items()}


def scope_table(cohort: dict, diagnostics: Mapping[str, str | Path], rates: dict[str, float]) -> pd.DataFrame:
    """One row per (model, subset): selected layer count, scope-averaged diagnostics, success loss in pp
    (`diagnostics`: model -> its diagnostics file)."""
    rows = []
    files = _checked(cohort, diagnostics)
    for model, spec in cohort["models"].items():
        diag = Diagnostics.read(files[model])
        prefix = f"{cohort['benchmark']}/{cohort['suite']}/{model}/"
        baseline = _rate(rates, prefix + spec["baseline"])
        for subset in map(functools.partial(get_subset, model), spec["subsets"]):
            names = diag.select(subset.only, subset.exclude)
            if len(names) != subset.layers:
                raise UserError(
                    f"{diag.path}: patterns only={subset.only} exclude={subset.exclude} of subset "
                    f"{model}/{subset.name} select {len(names)} layers, config/scopes.yaml says {subset.layers}"
                )
            cell = f"ablate-{diag.header['preset']}-{diag.header['scope']}-{subset.name}"
            rows.append({"model": model, "scope": subset.name, "cell": cell, "layers": len(names),
                         **diag.scope_average(names), "success_loss": baseline - _rate(rates, prefix + cell)})
    return pd.DataFrame(rows)


def _rate(rates: dict[str, float], ref: str) -> float:
    if ref not in rates:
        raise UserError(f"no success rate for cell {ref} in the success summary")
    return rates[ref]


def correlations(scopes: pd.DataFrame) -> pd.DataFrame:
    """Spearman rho (average ranks) between each diagnostic and success loss, per model."""
    from scipy.stats import spearmanr  # here, not at import: the workflow loads the cohort while it builds the DAG

    out = []
    for model, group in scopes.groupby("model", sort=False):
        row = {"model": model, "scopes": len(group)}
        for d in DIAGNOSTICS:
            row[d] = float(spearmanr(group[d], group["success_loss"]).statistic)
        out.append(row)
    return pd.DataFrame(out)


def _signed(x: float) -> str:
    return "--" if math.isnan(x) else f"{x:+.2f}"


def render_proxy_audit(rhos: pd.DataFrame, cohort: dict, sources: dict[str, dict]) -> Booktabs:
    header = ["Model", "Scopes", *COLUMNS.values()]
    rows = [
        [cohort["models"][r.model]["label"], str(r.scopes), *(_signed(getattr(r, d)) for d in DIAGNOSTICS)]
        for r in rhos.itertuples()
    ]
    provenance = "; ".join(
        f"{m}: {p.get('checkpoint')}@{str(p.get('checkpoint_revision'))[:7]}, seed {p.get('seed')}, "
        f"init states from {p.get('episodes_from')}, MuJoCo {p.get('mujoco')}, torch {p.get('torch')}, "
        f"code {p.get('vqb_commit') or 'not recorded'}"
        for m, p in sources.items()
    )
    caption = (
        "Exploratory Spearman correlations between saved layer-averaged diagnostics and success loss. "
        "Average ranks handle ties; repeated seeds are excluded. Scope sets overlap and per-model samples are "
        f"small, limiting interpretation. Diagnostics: {provenance}."
    ).replace("_", r"\_")
    return Booktabs("lrrrrr", [header], rows, caption, "tab:proxy_audit", size="small")


def write_proxy_audit(
    diagnostics: Mapping[str, str | Path],
    success_summary: str | Path,
    output: str | Path,
    scopes_output: str | Path | None = None,
    *,
    cohort: str | Path,
    html_output: str | Path | None = None,
) -> pd.DataFrame:
    """Snakemake entry: `tables/proxy_audit.tex` from `diagnostics` (model -> diagnostics file) of the cohort at
    `cohort` (`load_cohort`), the per-scope values as CSV to `scopes_output` (default: `<output>.scopes.csv`) and the
    browser page."""
    spec = load_cohort(cohort)
    rates = success_rates(success_summary)
    if not rates:
        raise UserError("the proxy audit needs a success summary (config key success_summary)")
    scopes = scope_table(spec, diagnostics, rates)
    rhos = correlations(scopes)
    sources = {m: Diagnostics.read(path).header["provenance"] for m, path in _checked(spec, diagnostics).items()}
    output = render_proxy_audit(rhos, spec, sources).write(output, html_output)
    with atomic_write(scopes_output or output.with_suffix(".scopes.csv")) as handle:
        scopes.to_csv(handle, index=False)
    return rhos
