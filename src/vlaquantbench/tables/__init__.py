"""The paper's tables as data: definitions from YAML, numbers from records, booktabs LaTeX out."""

from vlaquantbench.tables.definition import TableDefinition, load_table
from vlaquantbench.tables.latex import render_latex, table_rows, write_table
from vlaquantbench.tables.summary import SUMMARY_COLUMNS, summarize, write_summary

__all__ = [
    "SUMMARY_COLUMNS",
    "TableDefinition",
    "load_table",
    "render_latex",
    "summarize",
    "table_rows",
    "write_summary",
    "write_table",
]
