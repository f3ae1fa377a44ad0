"""A Snakemake job's log: all it prints goes to its rule's `log:` file; its cause leads the console.

    with job_log(snakemake):      # in workflow/scripts/<rule>.py
        write_table(...)

Output is redirected at the file-descriptor level, so simulator worker processes, MuJoCo and tqdm land
in the log too. When the job fails, the log ends with the traceback and one line `error: <cause>`;
the console gets that cause first, in one line naming the rule and the log, instead of a traceback
under a list of every input path. The workflow's `onerror:` handler repeats each failed job's cause
at the very end of the run (`failed_job_causes`).
"""

from __future__ import annotations

import logging
import os
import re
import sys
import traceback
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from vlaquantbench.errors import UserError

ERROR_PREFIX = "error: "
LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


def cause(err: BaseException) -> str:
    """What went wrong, for a person: a UserError's message, else `<Type>: <first line>`."""
    if isinstance(err, UserError):
        return str(err)
    text = str(err).strip().splitlines()
    return f"{type(err).__name__}: {text[0]}" if text else type(err).__name__


@contextmanager
def job_log(smk: Any) -> Iterator[Path]:
    """Run the block with stdout and stderr (fds 1 and 2) sent to `smk.log[0]`; on an exception, end
    the log with its cause, print the cause to the console and exit with status 1."""
    log = Path(smk.log[0])
    log.parent.mkdir(parents=True, exist_ok=True)
    sys.stdout.flush()
    sys.stderr.flush()
    console = os.dup(2), os.dup(1)
    with open(log, "w") as handle:
        os.dup2(handle.fileno(), 1)
        os.dup2(handle.fileno(), 2)
    logging.basicConfig(level=logging.INFO, format=LOG_FORMAT, stream=sys.stderr, force=True)
    failure = None
    try:
        yield log
    except Exception as err:  # KeyboardInterrupt and SystemExit keep their own handling
        traceback.print_exc()
        failure = cause(err)
        print(ERROR_PREFIX + failure.replace("\n", "\n" + ERROR_PREFIX), file=sys.stderr)
    finally:
        sys.stdout.flush()
        sys.stderr.flush()
        os.dup2(console[0], 2)
        os.dup2(console[1], 1)
        os.close(console[0])
        os.close(console[1])
    if failure is not None:
        print(f"{smk.rule} failed: {failure}\n  (full log: {log})", file=sys.stderr, flush=True)
        raise SystemExit(1)


_FAILED_LOG = re.compile(r"^\s*log: (?P<logs>.+?) \(check log file\(s\) for error details\)")
_FAILED_RULE = re.compile(r"^Error in rule (?P<rule>\S+):")


def failed_job_causes(snakemake_logs: str | Path | list[str | Path]) -> list[str]:
    """`<rule>: <cause> (log: <file>)` for every failed job in a Snakemake run's main log(s)."""
    logs = snakemake_logs if isinstance(snakemake_logs, list) else [snakemake_logs]
    lines, rule = [], None
    for line in (text for log in logs for text in _read_lines(Path(log))):
        if match := _FAILED_RULE.match(line):
            rule = match["rule"]
        elif (match := _FAILED_LOG.match(line)) and rule is not None:
            for log in match["logs"].split(", "):
                reasons = [r[len(ERROR_PREFIX):] for r in _read_lines(Path(log)) if r.startswith(ERROR_PREFIX)]
                lines.append(f"{rule}: {' / '.join(reasons) or 'no cause in its log'} (log: {log})")
            rule = None
    return lines


def _read_lines(path: Path) -> list[str]:
    return path.read_text(errors="replace").splitlines() if path.is_file() else []
