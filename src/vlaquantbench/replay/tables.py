"""Replay tables (paper `tab:replay_composition`, `tab:replay_allformats`, `tab:replay_bias`)
rendered from per-format `analysis.json` files."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

from vlaquantbench.replay.study import StudyResults, load_study, success_rates, with_formats
from vlaquantbench.tables.booktabs import MIDRULE, Booktabs


def composition_table(results: StudyResults) -> Booktabs:
    s = results.study
    small, large = s["recovery"]["smaller"], s["recovery"]["larger"]
    n_small, n_large = s["configurations"][small]["layers"], s["configurations"][large]["layers"]
    rows = []
    for fmt in s["formats"]:
        a = results.analyses[fmt]
        add, rec = a["additivity"], a["recovery"]
        rows.append([
            fmt, f"{add['norm_union_over_sum_of_norms']['median']:.2f}", f"{add['residual_over_union']['median']:.2f}",
            f"{add['cosine_union_vs_sum']['median']:.2f}",
            f"{rec[f'chunk_mae_{n_small}']:.3f} / {rec[f'chunk_mae_{n_large}']:.3f}",
            f"{100 * rec[f'frac_chunks_{n_large}_lower']:.1f}",
        ])
    n_chunks = results.analyses[s["formats"][0]]["additivity"]["n_chunks"]
    header = ["Format", "Norm ratio", "Residual", "Cosine", f"MAE: {n_small} / {n_large}", rf"{n_large} lower (\%)"]
    caption = (
        f"Replay composition statistics over {n_chunks} chunks. Norm ratio is "
        r"$\|e_{A\cup B}\|_2/(\|e_A\|_2+\|e_B\|_2)$; residual is $\|e_{A\cup B}-e_A-e_B\|_2/\|e_{A\cup B}\|_2$; "
        r"cosine compares $e_{A\cup B}$ with $e_A+e_B$. These columns report medians. "
        "MAE is averaged over normalized chunk coordinates and chunks."
    )
    return Booktabs("lrrrrr", [header], rows, caption, "tab:replay_composition", size="small")


def all_formats_table(results: StudyResults, rates: dict[str, float]) -> Booktabs:
    s = results.study
    rows = []
    for i, fmt in enumerate(s["all_formats_order"]):
        if i:
            rows.append(MIDRULE)
        for j, (name, conf) in enumerate(s["configurations"].items()):
            c = results.config(fmt, name)
            rate = rates.get(results.cell(fmt, name))
            sr = "--" if rate is None else f"{rate:.1f}"
            rows.append([
                fmt if j == 0 else "", conf["label"], str(c["quantized_layers"]), sr,
                f"{c['executed_action_mae']:.4f}", f"{c['chunk_mae_mean']:.3f}", f"{c['flow_step_divergence'][-1]:.3f}",
            ])
    header = ["Format", "Scope", r"\#L", r"SR (\%)", "Exec. MAE", "Chunk MAE", "State MAE"]
    caption = (
        "Replay across formats on the same held-out trajectories. Executed-action MAE uses environment units; "
        "chunk MAE uses the full normalized output chunk. State MAE is measured before the last flow update. "
        "SR comes from separate closed-loop evaluations of the matching cells, not the replay trajectories "
        "(-- where no record of that cell is available)."
    )
    return Booktabs("llrrrrr", [header], rows, caption, "tab:replay_allformats", size="small", tabcolsep="4pt")


def bias_table(results: StudyResults) -> Booktabs:
    s = results.study
    fmt = s["bias_format"]
    rows = []
    for name, conf in s["configurations"].items():
        c = results.config(fmt, name)
        signed = [f"{v:.3f}" for v in c["executed_action_signed_mean_per_dim"]]
        rows.append([conf["bias_label"], *signed, f"{c['downproj_tok_absmax_p99']:.2f}", f"{c['downproj_abs_kurtosis']:.1f}"])
    dims = len(results.config(fmt, s["baseline"])["executed_action_signed_mean_per_dim"])
    header = ["Scope", *(f"$a_{i + 1}$" for i in range(dims)), "Absmax P99", "$|x|$ kurt."]
    fp = results.config(fmt, s["baseline"])
    caption = (
        f"{fmt} signed action deviations (quantized minus full precision, environment units) and down-projection "
        "input summaries. Coordinates follow client order: translation, rotation, gripper. The full-precision input "
        f"summaries are {fp['downproj_tok_absmax_p99']:.2f} for token-absmax P99 and {fp['downproj_abs_kurtosis']:.1f} "
        "for absolute-value kurtosis. These are averages of per-call statistics, not quantiles of all concatenated tokens."
    )
    return Booktabs("l" + "r" * (dims + 2), [header], rows, caption, "tab:replay_bias", size="scriptsize", tabcolsep="3pt")


def write_replay_table(
    table: str,
    analyses: Mapping[str, str | Path],
    output: str | Path,
    *,
    study: str | Path,
    success_summary: str | Path | None = None,
    formats: list[str] | None = None,
    html_output: str | Path | None = None,
) -> str:
    """Snakemake entry: render one replay table (`composition`, `all_formats` or `bias`) of `study` (`load_study`)
    to `output` from `analyses` (format -> analysis.json, e.g. `analysis_files(folder, formats)`), and its browser
    page to `html_output`; returns the LaTeX."""
    results = StudyResults.from_files(analyses, with_formats(load_study(study), formats))
    renderers = {
        "composition": lambda: composition_table(results),
        "all_formats": lambda: all_formats_table(results, success_rates(success_summary)),
        "bias": lambda: bias_table(results),
    }
    rendered = renderers[table]()
    rendered.write(output, html_output)
    return rendered.latex()
