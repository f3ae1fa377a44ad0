"""Replay tables (paper `tab:replay_composition`, `tab:replay_allformats`, `tab:replay_bias`)
rendered from per-format `analysis.json` files."""

from __future__ import annotations

from pathlib import Path

from vlaquantbench.atomic import write_text
from vlaquantbench.replay.study import StudyResults, load_study, success_rates, with_formats


def _table(spec: str, header: str, rows: list[str], caption: str, label: str, size: str = "small") -> str:
    return "\n".join(
        [
            rf"\begin{{table}}[htbp]\centering\{size}",
            rf"\begin{{tabular}}{{{spec}}}\toprule",
            header + r"\midrule",
            *rows,
            r"\bottomrule\end{tabular}",
            rf"\caption{{{caption}}}",
            rf"\label{{{label}}}\end{{table}}",
            "",
        ]
    )


def composition_table(results: StudyResults) -> str:
    s = results.study
    small, large = s["recovery"]["smaller"], s["recovery"]["larger"]
    n_small, n_large = s["configurations"][small]["layers"], s["configurations"][large]["layers"]
    rows = []
    for fmt in s["formats"]:
        a = results.analyses[fmt]
        add, rec = a["additivity"], a["recovery"]
        rows.append(
            f"{fmt} & {add['norm_union_over_sum_of_norms']['median']:.2f} & {add['residual_over_union']['median']:.2f}"
            f" & {add['cosine_union_vs_sum']['median']:.2f}"
            f" & {rec[f'chunk_mae_{n_small}']:.3f} / {rec[f'chunk_mae_{n_large}']:.3f}"
            f" & {100 * rec[f'frac_chunks_{n_large}_lower']:.1f} \\\\"
        )
    n_chunks = results.analyses[s["formats"][0]]["additivity"]["n_chunks"]
    header = rf"Format & Norm ratio & Residual & Cosine & MAE: {n_small} / {n_large} & {n_large} lower (\%) \\"
    caption = (
        f"Replay composition statistics over {n_chunks} chunks. Norm ratio is "
        r"$\|e_{A\cup B}\|_2/(\|e_A\|_2+\|e_B\|_2)$; residual is $\|e_{A\cup B}-e_A-e_B\|_2/\|e_{A\cup B}\|_2$; "
        r"cosine compares $e_{A\cup B}$ with $e_A+e_B$. These columns report medians. "
        "MAE is averaged over normalized chunk coordinates and chunks."
    )
    return _table("lrrrrr", header, rows, caption, "tab:replay_composition")


def all_formats_table(results: StudyResults, rates: dict[str, float]) -> str:
    s = results.study
    rows = []
    for i, fmt in enumerate(s["all_formats_order"]):
        if i:
            rows.append(r"\midrule")
        for j, (name, conf) in enumerate(s["configurations"].items()):
            c = results.config(fmt, name)
            rate = rates.get(results.cell(fmt, name))
            sr = "--" if rate is None else f"{rate:.1f}"
            rows.append(
                f"{fmt if j == 0 else ''} & {conf['label']} & {c['quantized_layers']} & {sr}"
                f" & {c['executed_action_mae']:.4f} & {c['chunk_mae_mean']:.3f} & {c['flow_step_divergence'][-1]:.3f} \\\\"
            )
    header = r"Format & Scope & \#L & SR (\%) & Exec. MAE & Chunk MAE & State MAE \\"
    caption = (
        "Replay across formats on the same held-out trajectories. Executed-action MAE uses environment units; "
        "chunk MAE uses the full normalized output chunk. State MAE is measured before the last flow update. "
        "SR comes from separate closed-loop evaluations of the matching cells, not the replay trajectories "
        "(-- where no record of that cell is available)."
    )
    return _table("llrrrrr", header, rows, caption, "tab:replay_allformats").replace(
        r"\centering\small", r"\centering\small\setlength{\tabcolsep}{4pt}", 1
    )


def bias_table(results: StudyResults) -> str:
    s = results.study
    fmt = s["bias_format"]
    rows = []
    for name, conf in s["configurations"].items():
        c = results.config(fmt, name)
        signed = " & ".join(f"{v:.3f}" for v in c["executed_action_signed_mean_per_dim"])
        rows.append(
            f"{conf['bias_label']} & {signed} & {c['downproj_tok_absmax_p99']:.2f} & {c['downproj_abs_kurtosis']:.1f} \\\\"
        )
    dims = len(results.config(fmt, s["baseline"])["executed_action_signed_mean_per_dim"])
    header = "Scope & " + " & ".join(f"$a_{i + 1}$" for i in range(dims)) + r" & Absmax P99 & $|x|$ kurt. \\"
    fp = results.config(fmt, s["baseline"])
    caption = (
        f"{fmt} signed action deviations (quantized minus full precision, environment units) and down-projection "
        "input summaries. Coordinates follow client order: translation, rotation, gripper. The full-precision input "
        f"summaries are {fp['downproj_tok_absmax_p99']:.2f} for token-absmax P99 and {fp['downproj_abs_kurtosis']:.1f} "
        "for absolute-value kurtosis. These are averages of per-call statistics, not quantiles of all concatenated tokens."
    )
    return _table("l" + "r" * (dims + 2), header, rows, caption, "tab:replay_bias", size="scriptsize").replace(
        r"\centering\scriptsize", r"\centering\scriptsize\setlength{\tabcolsep}{3pt}", 1
    )


def write_replay_table(
    table: str,
    analysis_dir: str | Path,
    output: str | Path,
    study: str | Path = "pi05_libero_spatial",
    success_summary: str | Path | None = None,
    formats: list[str] | None = None,
) -> str:
    """Snakemake entry: render one replay table (`composition`, `all_formats` or `bias`) to `output`."""
    results = StudyResults.from_dir(analysis_dir, with_formats(load_study(study), formats))
    renderers = {
        "composition": lambda: composition_table(results),
        "all_formats": lambda: all_formats_table(results, success_rates(success_summary)),
        "bias": lambda: bias_table(results),
    }
    text = renderers[table]()
    write_text(output, text)
    return text
