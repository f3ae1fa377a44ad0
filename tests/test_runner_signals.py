"""runner.signals: SIGTERM raises Terminated (a KeyboardInterrupt with exit status 128 + 15) inside
`sigterm_interrupts`, once; a SIGTERM the process was started with ignored stays ignored."""

import signal
import subprocess
import sys

PROBE = """
import os, signal
from vlaquantbench.runner.signals import Terminated, sigterm_interrupts
try:
    with sigterm_interrupts():
        try:
            os.kill(os.getpid(), signal.SIGTERM)
            print("ran on", flush=True)
        except KeyboardInterrupt as stop:
            print(type(stop).__name__, 128 + stop.signum, flush=True)
            os.kill(os.getpid(), signal.SIGTERM)  # a second SIGTERM while cleaning up
            print("cleaned up", flush=True)
except Terminated:
    print("escaped", flush=True)
print("restored", signal.getsignal(signal.SIGTERM) == signal.SIG_DFL)
"""


def probe(ignored):
    preexec = (lambda: signal.signal(signal.SIGTERM, signal.SIG_IGN)) if ignored else None
    return subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, timeout=60,
                          preexec_fn=preexec).stdout.splitlines()


def test_sigterm_raises_terminated_once_and_the_default_returns_after():
    assert probe(ignored=False) == ["Terminated 143", "cleaned up", "restored True"]


def test_a_sigterm_ignored_by_the_parent_stays_ignored():
    assert probe(ignored=True) == ["ran on", "restored False"]
