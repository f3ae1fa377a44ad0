"""Loaded by every Python process of an audited Snakemake run (tests/file_audit.py puts this folder on
PYTHONPATH and names a folder in VQB_FILE_AUDIT). In a job script's process it records, through
Python's audit hooks, every file the job opens, lists, renames or removes, and at exit writes them
with the job's declared input, output, log and `params.state` files to `<VQB_FILE_AUDIT>/<pid>.json`.
Files opened by C++ libraries (pyarrow's parquet reader) bypass `open` and are not seen."""

import atexit
import json
import os
import sys

_AUDIT_DIR = os.environ.get("VQB_FILE_AUDIT")
_WRITE_FLAGS = os.O_WRONLY | os.O_RDWR | os.O_CREAT | os.O_APPEND | os.O_TRUNC
_events: list[list] = []
_recording = [True]


def _path(value):
    return os.fsdecode(value) if isinstance(value, (str, bytes, os.PathLike)) else None


def _hook(event: str, args: tuple) -> None:
    if not _recording[0]:
        return
    if event == "open":
        path, mode, flags = args
        path = _path(path)
        if path is not None:
            writes = any(c in (mode or "") for c in "wxa+") if mode else bool((flags or 0) & _WRITE_FLAGS)
            _events.append(["write" if writes else "read", os.path.abspath(path)])
    elif event in ("os.listdir", "os.scandir") and _path(args[0]) is not None:
        _events.append(["list", os.path.abspath(_path(args[0]))])
    elif event in ("os.rename", "os.replace") and _path(args[1]) is not None:
        _events.append(["write", os.path.abspath(_path(args[1]))])
    elif event == "os.remove" and _path(args[0]) is not None:
        _events.append(["remove", os.path.abspath(_path(args[0]))])


def _dump() -> None:
    _recording[0] = False
    job = getattr(sys.modules.get("__main__"), "snakemake", None)
    if type(job).__name__ != "Snakemake":  # Snakemake itself, or any other process of the run
        return
    state = getattr(job.params, "state", None) or {}
    declared = {"input": list(job.input), "output": list(job.output), "log": list(job.log),
                "state": list(state.values())}
    absolute = {kind: [os.path.abspath(p) for p in paths] for kind, paths in declared.items()}
    with open(os.path.join(_AUDIT_DIR, f"{os.getpid()}.json"), "w") as handle:
        json.dump({"rule": job.rule, "declared": absolute, "events": _events,
                   "import_path": [os.path.abspath(p) for p in sys.path]}, handle)


if _AUDIT_DIR:
    sys.addaudithook(_hook)
    atexit.register(_dump)
