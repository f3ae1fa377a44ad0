"""The paper's tables as data: definitions from YAML, numbers from records, booktabs LaTeX out.

Names are imported on first access (PEP 562), so a job that only needs the LaTeX writer (`tables.booktabs`,
e.g. tab:vla_params) does not import pandas through the record readers.
"""

from vlaquantbench.lazy_exports import lazy_exports

_EXPORTS = {
    "definition": ["TableDefinition", "load_table"],
    "latex": ["render_latex", "table_rows", "write_table"],
    "summary": ["SUMMARY_COLUMNS", "summarize", "write_summary"],
}

__all__ = sorted(name for names in _EXPORTS.values() for name in names)
__getattr__ = lazy_exports(__name__, _EXPORTS)
