"""Paper `fig:replay_formats`: (a) chunk error of the smaller vs the larger scope per format,
(b) median and IQR of the per-chunk norm ratio ‖e_A∪B‖/(‖e_A‖+‖e_B‖) per format."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import matplotlib
import matplotlib.ticker

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from vlaquantbench.atomic import atomic_write  # noqa: E402
from vlaquantbench.replay.study import StudyResults, load_study, with_formats  # noqa: E402


def plot_formats(results: StudyResults, output: str | Path) -> Path:
    s = results.study
    formats = s["formats"]
    small, large = s["recovery"]["smaller"], s["recovery"]["larger"]
    n_small, n_large = s["configurations"][small]["layers"], s["configurations"][large]["layers"]
    x = np.arange(len(formats))

    fig, (ax_a, ax_b) = plt.subplots(1, 2, figsize=(7.0, 2.6))
    for offset, n, color in ((-0.2, n_small, "tab:red"), (0.2, n_large, "tab:blue")):
        ax_a.bar(x + offset, [results.analyses[f]["recovery"][f"chunk_mae_{n}"] for f in formats], 0.4,
                 label=f"{n} layers", color=color)
    ax_a.set_xticks(x, formats)
    ax_a.set_yscale("log")
    ax_a.yaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax_a.set_ylabel("normalized chunk MAE")
    ax_a.set_title("(a) recovery before feedback", fontsize=9)
    ax_a.legend(fontsize=7, frameon=False)

    ratio = [results.analyses[f]["additivity"]["norm_union_over_sum_of_norms"] for f in formats]
    med = np.array([r["median"] for r in ratio])
    lo, hi = np.array([r["iqr"][0] for r in ratio]), np.array([r["iqr"][1] for r in ratio])
    ax_b.errorbar(x, med, yerr=[med - lo, hi - med], fmt="o", color="black", capsize=3)
    ax_b.axhline(1.0, linestyle="--", color="gray", linewidth=1)
    ax_b.set_xticks(x, formats)
    ax_b.set_ylabel(r"$\|e_{A\cup B}\|/(\|e_A\|+\|e_B\|)$")
    ax_b.set_title("(b) norm ratio, median and IQR", fontsize=9)

    fig.tight_layout()
    with atomic_write(output, "wb") as handle:
        fig.savefig(handle, format="pdf")
    plt.close(fig)
    return output


def write_replay_figure(
    analyses: Mapping[str, str | Path],
    output: str | Path,
    *,
    study: str | Path,
    formats: list[str] | None = None,
) -> Path:
    """Snakemake entry: `fig:replay_formats` from `analyses` (format -> analysis.json) of `study` (`load_study`)."""
    return plot_formats(StudyResults.from_files(analyses, with_formats(load_study(study), formats)), output)
