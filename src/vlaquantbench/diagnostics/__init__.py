"""Layer diagnostics and the proxy audit (paper App. `app:diagnostics`, `tab:proxy_audit`).

    measures.py     per-call kurtosis, relative output/activation error, dispersion
    collect.py      collect them on a replay recording, with provenance (authors' file layout)
    files.py        read and validate such files; apply include/exclude patterns to layer names
    proxy_audit.py  Spearman (average ranks) of scope-averaged diagnostics vs success loss
"""
