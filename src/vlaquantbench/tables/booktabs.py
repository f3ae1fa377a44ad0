"""The one table writer: a table's rows and caption in, booktabs LaTeX and a browser page out.

Every table of the project (record tables, replay tables, the proxy audit) builds a `Booktabs`
and renders it here, so layout rules live in one place. `html()` gives the same table as a small
self-contained page (the HTML report shows it; the `.tex` is what a paper includes).
"""

from __future__ import annotations

import html
import re
from dataclasses import dataclass, field
from pathlib import Path

from vlaquantbench.atomic import write_text

MIDRULE = None  # a row that is a horizontal rule
ENVIRONMENTS = ("tabular", "longtable")


@dataclass(frozen=True)
class Booktabs:
    align: str
    header: list[list[str]]  # one list per header line
    rows: list[list[str] | None]  # a list of cells per line, or MIDRULE
    caption: str
    label: str  # e.g. tab:lattice
    environment: str = "tabular"
    size: str = ""  # e.g. "small": \small inside the float
    tabcolsep: str = ""  # e.g. "4pt"
    notes: list[str] = field(default_factory=list)  # shown under the HTML table only (data source, manifest)

    def latex(self) -> str:
        header = "\n".join(_line(cells) for cells in self.header)
        body = "\n".join(r"\midrule" if row is MIDRULE else _line(row) for row in self.rows)
        caption = rf"\caption{{{self.caption}}}\label{{{self.label}}}"
        layout = "".join(
            [rf"\{self.size}" if self.size else "", rf"\setlength{{\tabcolsep}}{{{self.tabcolsep}}}" if self.tabcolsep else ""]
        )
        if self.environment == "longtable":  # a longtable is not a float: no size or layout inside
            return (
                f"\\begin{{longtable}}{{{self.align}}}\n{caption}\\\\\n"
                f"\\toprule\n{header}\n\\midrule\\endfirsthead\n"
                f"\\toprule\n{header}\n\\midrule\\endhead\n"
                f"\\bottomrule\\endfoot\n{body}\n\\end{{longtable}}\n"
            )
        return (
            f"\\begin{{table}}[htbp]\n\\centering{layout}\n\\begin{{tabular}}{{{self.align}}}\n\\toprule\n{header}\n"
            f"\\midrule\n{body}\n\\bottomrule\n\\end{{tabular}}\n{caption}\n\\end{{table}}\n"
        )

    def html(self) -> str:
        head = "".join(_html_row(cells, "th") for cells in self.header)
        body = "".join(
            f'<tr class="rule"><td colspan="{_width(self)}"></td></tr>' if row is MIDRULE else _html_row(row, "td")
            for row in self.rows
        )
        notes = "".join(f"<p class=\"note\">{html.escape(note)}</p>" for note in self.notes)
        return (
            f'<!DOCTYPE html>\n<html><head><meta charset="utf-8"><title>{self.label}</title><style>{_CSS}</style></head>'
            f'<body><table id="{self.label}"><caption>{_text(self.caption)}</caption><thead>{head}</thead>'
            f"<tbody>{body}</tbody></table>{notes}</body></html>\n"
        )

    def write(self, output: str | Path, html_output: str | Path | None = None) -> Path:
        """Write the `.tex` (and the page, when `html_output` is given) atomically."""
        if html_output is not None:
            write_text(html_output, self.html())
        return write_text(output, self.latex())


def _line(cells: list[str]) -> str:
    return " & ".join(cells) + r" \\"


def _width(table: Booktabs) -> int:
    return max(len(re.findall(r"[lrcp]", re.sub(r"\{[^}]*\}", "", table.align))), 1)


_CSS = (
    "body{font-family:serif;margin:1em}table{border-collapse:collapse;border-top:2px solid #000;"
    "border-bottom:2px solid #000}thead tr:last-child th{border-bottom:1px solid #000}th,td{padding:2px 8px;"
    "text-align:right}th:first-child,td:first-child{text-align:left}tr.rule td{border-top:1px solid #000;padding:0}"
    "caption{caption-side:bottom;text-align:left;max-width:60em;padding-top:.5em}.note{color:#444;font-size:90%}"
)

_MULTICOLUMN = re.compile(r"^\\multicolumn\{(\d+)\}\{[^}]*\}\{(.*)\}$", re.S)
_MULTIROW = re.compile(r"^\\multirow\{\d+\}\{[^}]*\}\{(.*)\}$", re.S)


def _html_row(cells: list[str], tag: str) -> str:
    out = []
    for cell in cells:
        cell = cell.strip()
        span = ""
        if match := _MULTICOLUMN.match(cell):
            span, cell = f' colspan="{match.group(1)}"', match.group(2)
        if match := _MULTIROW.match(cell):
            cell = match.group(1)
        out.append(f"<{tag}{span}>{_text(cell)}</{tag}>")
    return f"<tr>{''.join(out)}</tr>"


_SYMBOLS = {r"\pi": "π", r"\alpha": "α", r"\Delta": "Δ", r"\rightarrow": "→", r"\times": "×", r"\pm": "±",
            r"\cup": "∪", r"\|": "‖", r"\leq": "≤", r"\geq": "≥"}  # fmt: skip
_WRAPPERS = {"textbf": "b", "texttt": "code", "path": "code", "emph": "i", "textit": "i", "mathrm": "span", "text": "span"}


def _text(latex: str) -> str:
    """LaTeX cell text as HTML, for the handful of constructs the tables use."""
    text = html.escape(latex, quote=False)
    for command, tag in _WRAPPERS.items():
        pattern = re.compile(rf"\\{command}\{{([^{{}}]*(?:\{{[^{{}}]*\}}[^{{}}]*)*)\}}")
        while pattern.search(text):
            text = pattern.sub(rf"<{tag}>\1</{tag}>", text)
    for symbol, char in _SYMBOLS.items():
        text = text.replace(symbol, char)
    text = re.sub(r"_\{([^{}]*)\}", r"<sub>\1</sub>", text)
    text = re.sub(r"\^\{([^{}]*)\}", r"<sup>\1</sup>", text)
    text = re.sub(r"\\(?:quad|qquad)\s*", "\u2003", text)
    text = re.sub(r"\\(?:ref|label)\{[^}]*\}", "", text)
    text = text.replace("``", "“").replace("''", "”").replace("--", "–").replace("~", " ").replace(r"\ ", " ")
    text = re.sub(r"\\([%#_&$])", r"\1", text)
    text = re.sub(r"(?<!\\)\$", "", text)
    text = re.sub(r"\\[a-zA-Z]+\*?(\{[^}]*\})*", "", text)  # remaining layout commands (\small, \setlength ...)
    return text.replace("{", "").replace("}", "")
