"""The paper's tables as data: definitions from YAML, numbers from records, booktabs LaTeX out.

Names are imported on first access (PEP 562), so a job that only needs the LaTeX writer (`tables.booktabs`,
e.g. tab:vla_params) does not import pandas through the record readers.
"""

import importlib

_EXPORTS = {
    "SUMMARY_COLUMNS": "summary",
    "TableDefinition": "definition",
    "load_table": "definition",
    "render_latex": "latex",
    "summarize": "summary",
    "table_rows": "latex",
    "write_summary": "summary",
    "write_table": "latex",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name not in _EXPORTS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"{__name__}.{_EXPORTS[name]}"), name)
