"""Snakemake's HTML report of the paper targets, opened in a real headless Chromium: every table shows.

Chromium is driven over the DevTools protocol on a pipe (`--remote-debugging-pipe`: JSON messages
ended by NUL on file descriptors 3 and 4), so no websocket client is needed. The report's own
app shows each table the way a reader's click does; the text is read inside the table's frame.
"""

import json
import os
import shutil
import subprocess
import sys
import time

import pytest
from test_tables_workflow import layout

from paths import ROOT, RECORDS

pytestmark = pytest.mark.slow
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
TABLES = ("lattice", "components", "exp1_xvla")  # from records, from the summary, with unavailable rows


class DevTools:
    """A minimal DevTools-protocol client over Chromium's debugging pipe."""

    def __init__(self, binary: str, profile):
        commands_read, self._commands = os.pipe()
        self._replies, replies_write = os.pipe()

        def child_fds():  # Chromium reads commands on fd 3 and writes replies on fd 4
            high = os.dup(commands_read), os.dup(replies_write)  # first out of the way of 3 and 4
            os.dup2(high[0], 3)
            os.dup2(high[1], 4)

        self.process = subprocess.Popen(
            [binary, "--headless", "--no-sandbox", "--disable-gpu", "--remote-debugging-pipe",
             f"--user-data-dir={profile}", "--window-size=1400,1000", "about:blank"],
            close_fds=False, preexec_fn=child_fds,  # (close_fds would close 3 and 4 after preexec_fn)
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )  # fmt: skip
        os.close(commands_read)
        os.close(replies_write)
        self._buffer, self._next_id, self.events = b"", 0, []

    def call(self, method: str, session: str | None = None, timeout: float = 60, **params) -> dict:
        self._next_id += 1
        message = {"id": self._next_id, "method": method, "params": params, **({"sessionId": session} if session else {})}
        os.write(self._commands, json.dumps(message).encode() + b"\0")
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            reply = self._read()
            if reply.get("id") == self._next_id:
                if "error" in reply:
                    raise RuntimeError(f"{method}: {reply['error']}")
                return reply["result"]
            self.events.append(reply)
        raise TimeoutError(method)

    def _read(self) -> dict:
        while b"\0" not in self._buffer:
            chunk = os.read(self._replies, 1 << 16)
            if not chunk:
                raise RuntimeError("Chromium closed its debugging pipe")
            self._buffer += chunk
        message, self._buffer = self._buffer.split(b"\0", 1)
        return json.loads(message)

    def evaluate(self, session: str, expression: str, context: int | None = None):
        extra = {"contextId": context} if context else {}
        result = self.call("Runtime.evaluate", session, expression=expression, returnByValue=True, awaitPromise=True, **extra)
        if "exceptionDetails" in result:
            raise RuntimeError(f"{expression[:80]}: {result['exceptionDetails']}")
        return result["result"].get("value")

    def close(self):
        self.process.kill()
        self.process.wait()


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("report")
    workdir = layout(tmp, RECORDS)
    targets = [f"tables/{name}.tex" for name in TABLES] + ["figures/scope_recovery.pdf"]
    base = [sys.executable, "-m", "snakemake", *targets, "--cores", "2", "--snakefile", str(ROOT / "Snakefile"),
            "--directory", str(workdir), "--configfile", str(ROOT / "config" / "reference.yaml")]  # fmt: skip
    for extra in ([], ["--report", str(workdir / "report.html")]):  # build, then report what was built
        run = subprocess.run([*base, *extra], capture_output=True, text=True, timeout=600)
        assert run.returncode == 0, run.stderr[-3000:]
    return workdir / "report.html"


def show_each_table(tools: DevTools, session: str) -> dict[str, dict]:
    """Open every result of the report's Tables category as a reader would; return what each frame shows."""
    paths = tools.evaluate(session, "Object.values(categories['Tables']).flat()")
    shown = {}
    for path in paths:
        tools.evaluate(session, f"app.setView({{content: 'html', contentPath: results[{json.dumps(path)}].data_uri, "
                                f"resultPath: {json.dumps(path)}}}); true")  # fmt: skip
        time.sleep(0.5)
        frames = tools.call("Page.getFrameTree", session)["frameTree"].get("childFrames", [])
        assert len(frames) == 1, f"{path}: expected the table's frame, got {len(frames)}"
        context = tools.call("Page.createIsolatedWorld", session, frameId=frames[0]["frame"]["id"])["executionContextId"]
        shown[path] = tools.evaluate(session, """(() => {
            const table = document.querySelector('table');
            if (!table) return {text: document.body ? document.body.innerText : '', width: 0, height: 0};
            const box = table.getBoundingClientRect();
            return {text: table.innerText, page: document.body.innerText, width: box.width, height: box.height};
        })()""", context)  # fmt: skip
    return shown


@pytest.mark.skipif(CHROMIUM is None, reason="no chromium: .ci/run installs the Debian package `chromium`")
def test_report_shows_every_table_in_a_real_browser(report, tmp_path):
    tools = DevTools(CHROMIUM, tmp_path / "profile")
    try:
        target = tools.call("Target.getTargets")["targetInfos"][0]["targetId"]
        session = tools.call("Target.attachToTarget", targetId=target, flatten=True)["sessionId"]
        tools.call("Page.enable", session)
        tools.call("Page.navigate", session, url=report.as_uri())
        deadline = time.monotonic() + 60
        while not tools.evaluate(session, "typeof app !== 'undefined' && typeof categories !== 'undefined'"):
            assert time.monotonic() < deadline, "the report's app did not start"
            time.sleep(0.2)
        assert tools.evaluate(session, "Object.keys(categories).sort()") == ["Figures", "Tables"]
        shown = show_each_table(tools, session)
    finally:
        tools.close()
    assert sorted(shown) == sorted(f"tables/{name}.html" for name in TABLES)
    for path, table in shown.items():
        assert table["width"] > 100 and table["height"] > 50, (path, table)
        assert "Data source: episode records in ../shared/reference/records" in table["page"], path
        assert "Records checked against manifest manifests/reference.tsv (SHA-256 " in table["page"], path
    assert "attention + adaRMS\t108\t1.5 [1,4]\t-97.5" in shown["tables/lattice.html"]["text"]
    assert "OpenVLA-OFT\t100.0\t0.0\t0.0\t0.0" in shown["tables/components.html"]["text"]
    assert "CALVIN ABC→D (Avg. Len.)\t4.28\t4.13\t4.20\t4.25\t0.00\t4.20\t4.27" in shown["tables/exp1_xvla.html"]["text"]
    assert "SIMPLER-VM (SR %)" + "\tn/a" * 7 in shown["tables/exp1_xvla.html"]["text"]
    assert "VLABench (Avg. PS %)" + "\tn/a" * 7 in shown["tables/exp1_xvla.html"]["text"]
